#!/usr/bin/env bash
# The Python side: builds the `pixlrelight` wheel (crates/pixl-py, maturin, abi3), checks that it
# installs in a fresh venv and imports, then runs its pytest suite and the ComfyUI nodes' tests
# against the `pixl` binary of the same checkout (built here if missing). Run by .ci/run after
# `cargo test --workspace --locked`, whose build it reuses.
#
# usage: scripts/test-python.sh
set -euo pipefail
cd "$(dirname "$0")/.."
VENV=target/py-test
rm -rf "$VENV" target/wheels
python3 -m venv "$VENV"
"$VENV/bin/pip" install -q --disable-pip-version-check maturin numpy pytest pillow
cargo build -q --locked -p pixl-cli
"$VENV/bin/maturin" build -q --locked -m crates/pixl-py/Cargo.toml --profile dev -o target/wheels
WHEEL=$(ls target/wheels/pixlrelight-*.whl)
# A fresh venv with nothing but the wheel (numpy comes with it).
FRESH=target/py-fresh
rm -rf "$FRESH"
python3 -m venv "$FRESH"
"$FRESH/bin/pip" install -q --disable-pip-version-check "$WHEEL"
(cd /tmp && "$OLDPWD/$FRESH/bin/python" -c "import pixlrelight; print('pixlrelight', pixlrelight.__version__)")
"$VENV/bin/pip" install -q --disable-pip-version-check --force-reinstall --no-deps "$WHEEL"
"$VENV/bin/python" -m pytest -q crates/pixl-py/tests integrations/comfyui/tests
