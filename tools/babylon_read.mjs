// Reads a .glb with Babylon.js's own KHR_gaussian_splatting loader (headless, NullEngine) and
// prints, per Gaussian-splatting mesh, the splat data Babylon decoded, as JSON:
// { meshes: [{ name, count, position: [...], scale: [...], rgba: [...], quat_wxyz: [...] }] }.
// Positions and scales are the float32 values Babylon keeps; colour, opacity and rotation are
// Babylon's 8-bit encodings. Usage: node tools/babylon_read.mjs FILE.glb
import { readFile } from 'node:fs/promises';
import { NullEngine } from '@babylonjs/core/Engines/nullEngine.js';
import { Scene } from '@babylonjs/core/scene.js';
import { LoadAssetContainerAsync } from '@babylonjs/core/Loading/sceneLoader.js';
import { GaussianSplattingMesh } from '@babylonjs/core/Meshes/GaussianSplatting/gaussianSplattingMesh.js';
import '@babylonjs/loaders/glTF/2.0/index.js';

const file = process.argv[2];
const captured = new Map();
// Record what the loader decoded before Babylon uploads it to (here absent) GPU textures.
const original = GaussianSplattingMesh.prototype.updateDataAsync;
GaussianSplattingMesh.prototype.updateDataAsync = function (data, ...rest) {
  captured.set(this, data.slice(0));
  return original.call(this, data, ...rest).catch(() => undefined);
};

const engine = new NullEngine();
const scene = new Scene(engine);
const bytes = new Uint8Array(await readFile(file));
const container = await LoadAssetContainerAsync(bytes, scene, { pluginExtension: '.glb' });
const meshes = [];
for (const mesh of container.meshes) {
  const data = captured.get(mesh);
  if (!data) continue;
  const f = new Float32Array(data);
  const u = new Uint8Array(data);
  const count = data.byteLength / 32;
  const out = { name: mesh.name, count, position: [], scale: [], rgba: [], quat_wxyz: [] };
  for (let i = 0; i < count; i++) {
    out.position.push(f[i * 8], f[i * 8 + 1], f[i * 8 + 2]);
    out.scale.push(f[i * 8 + 3], f[i * 8 + 4], f[i * 8 + 5]);
    for (let k = 0; k < 4; k++) out.rgba.push(u[i * 32 + 24 + k]);
    for (let k = 0; k < 4; k++) out.quat_wxyz.push(u[i * 32 + 28 + k]);
  }
  meshes.push(out);
}
console.log(JSON.stringify({ meshes }));
engine.dispose();
