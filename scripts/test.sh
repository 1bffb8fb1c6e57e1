#!/usr/bin/env bash
# Runs every test: formatting and lints, the Rust tests (unit, integration, external readers),
# the Python tests (Blender toolkit, USD checks with usd-core), and a short fuzz run.
set -euo pipefail
cd "$(dirname "$0")/.."
QUIET=1 bash scripts/setup.sh

echo "== cargo fmt --check"
cargo fmt --all -- --check
echo "== cargo clippy"
cargo clippy --locked --all-targets --quiet -- -D warnings
echo "== cargo test"
cargo test --locked --quiet
echo "== pytest"
LIGHTFUSE_BIN="$PWD/target/release/lightfuse" .venv/bin/python -m pytest -q blender/tests tests/python
echo "== fuzz (short)"
bash scripts/fuzz.sh "${FUZZ_SECONDS:-60}"
