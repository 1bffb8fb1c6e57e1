#!/usr/bin/env bash
# Runs every test: formatting and lints, the Rust tests (unit, integration, external readers),
# the Python tests (Blender toolkit, USD checks with usd-core), and a short fuzz run.
set -euo pipefail
cd "$(dirname "$0")/.."
QUIET=1 bash scripts/setup.sh
# The `denoise` feature links Open Image Denoise from the venv's pyoidn (as scripts/setup.sh).
source scripts/oidn_env.sh
# Chromium and its driver (Debian packages) for the browser test of the evaluation report.
if ! command -v chromium >/dev/null || ! command -v chromedriver >/dev/null; then
  echo "== installing chromium and chromium-driver (Debian) for the report's browser test"
  SUDO=; [ "$(id -u)" = 0 ] || SUDO=sudo
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq --no-install-recommends chromium chromium-driver >/dev/null
fi

echo "== cargo fmt --check"
cargo fmt --all -- --check
echo "== cargo clippy (with and without --features denoise)"
cargo clippy --locked --all-targets --features denoise --quiet -- -D warnings
cargo clippy --locked --all-targets --quiet -- -D warnings
echo "== cargo doc (the library's doc links resolve)"
RUSTDOCFLAGS="-D warnings" cargo doc --locked --no-deps --lib --quiet
echo "== cargo test"
cargo test --locked --features denoise --quiet
echo "== pytest"
LIGHTFUSE_BIN="$PWD/target/release/lightfuse" .venv/bin/python -m pytest -q blender/tests tests/python
echo "== fuzz (short)"
bash scripts/fuzz.sh "${FUZZ_SECONDS:-60}"
