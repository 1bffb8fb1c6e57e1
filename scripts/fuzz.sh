#!/usr/bin/env bash
# Fuzzes the glTF reader for N seconds (default 60) from seeds written by the library itself.
# cargo-fuzz needs nightly flags; RUSTC_BOOTSTRAP=1 lets this machine's one stable toolchain
# accept them.
set -euo pipefail
cd "$(dirname "$0")/.."
secs=${1:-60}
if ! cargo fuzz --version >/dev/null 2>&1; then
  echo "fuzz: installing cargo-fuzz" >&2
  cargo install --locked --quiet cargo-fuzz
fi
seeds=fuzz/corpus/gltf_reader
mkdir -p "$seeds"
# With the venv there, the seeds are written by the release library as scripts/setup.sh builds
# it (the `denoise` feature), rather than by a second build of it without.
features=()
if [ -x .venv/bin/python ]; then
  source scripts/oidn_env.sh
  features=(--features denoise)
fi
cargo run --quiet --release "${features[@]}" --example write_test_scene -- "$seeds/seed.glb" 4 2>/dev/null
cargo run --quiet --release "${features[@]}" --example write_test_scene -- "$seeds/seed.gltf" 4 2>/dev/null
rm -rf "$seeds"/seed.env "$seeds"/seed.bin "$seeds"/*.expected.json
export RUSTC_BOOTSTRAP=1
cargo fuzz run gltf_reader --sanitizer none -- -max_total_time="$secs" -rss_limit_mb=3072 -max_len=65536 2>&1 | tail -n 5
