// Validates glTF files with the Khronos glTF-Validator and prints its report as JSON.
// Usage: node tools/validate_gltf.mjs FILE [--override CODE=SEVERITY ...]
// Severity: 0 error, 1 warning, 2 info, 3 hint. Exit code 0 when the report has no errors.
import { readFile } from 'node:fs/promises';
import path from 'node:path';
import validator from 'gltf-validator';

const args = process.argv.slice(2);
const file = args[0];
const severityOverrides = {};
for (let i = 1; i < args.length; i++) {
  if (args[i] === '--override') {
    const [code, sev] = args[++i].split('=');
    severityOverrides[code] = Number(sev);
  }
}
const data = await readFile(file);
const report = await validator.validateBytes(new Uint8Array(data), {
  uri: path.basename(file),
  maxIssues: 0,
  severityOverrides,
  externalResourceFunction: (uri) =>
    readFile(path.join(path.dirname(file), decodeURIComponent(uri))).then((b) => new Uint8Array(b)),
});
console.log(JSON.stringify(report, null, 1));
process.exit(report.issues.numErrors === 0 ? 0 : 1);
