#!/usr/bin/env bash
# Checks the gradients of the PIXLRelight training loss computed by `pixl` (candle, f32) against
# an independent float64 PyTorch computation (scripts/bench/pixl_torch.py), parameter by parameter.
#
# For each config it:
#   1. writes fresh weights (`pixl model init`) and perturbs every tensor with seeded noise
#      (`pixl_torch.py perturb`), so that every part of the network, the zero-initialised modulation
#      conv included, receives a non-zero gradient;
#   2. writes random inputs src (B, 3, H, W), ct (B, 9, H, W), tgt (B, 3, H, W), uniform in [0, 1)
#      (`train_grads --make-inputs`; the default size is not a multiple of 16, so the edge padding
#      and the position-embedding resize are differentiated too);
#   3. computes the loss and every parameter's gradient with pixl's training path
#      (crates/pixl-train/examples/train_grads.rs: the checkpoint loaded into a trainable VarMap,
#      `pixl_train::recompute::plain` with the L1 objective, divisor 1: the loss of
#      `pixl bench train-step`, before clipping and AdamW) and with `pixl_torch.py grads` (the
#      same loss, model and inputs in float64);
#   4. compares them (`pixl_torch.py compare-grads`): per tensor the relative error
#      ‖pixl − torch‖₂ / ‖torch‖₂; prints the worst tensors and a summary, and fails if any tensor
#      is above --tol or missing.
# Exits non-zero if any config fails.
#
# usage: scripts/check-train-grads.sh [--config small] [--size WxH] [--batch B] [--tol X]
#                                     [--seed S] [--threads T] [--top N] [--work DIR]
#   --config   preset, or comma-separated presets (default small)
#   --size     input size WIDTHxHEIGHT (default 200x136)
#   --batch    images (default 2)
#   --tol      largest relative L2 error allowed per tensor (default 1e-4)
#   --seed     seed of the weight noise and of the inputs (default 0)
#   --threads  threads for both (RAYON_NUM_THREADS; torch.set_num_threads) (default 2)
#   --top      worst tensors printed per config (default 10)
#   --work     folder for weights, inputs and gradients (default: a temporary folder, removed)
# env:
#   PIXL_BIN          a pixl binary for `pixl model init`; else `cargo build --release -p pixl-cli`
#   TRAIN_GRADS_BIN   the train_grads example binary; else
#                     `cargo build --release -p pixl-train --example train_grads` is run
#   PYTHON, PIXL_TORCH_VENV, TORCH_INDEX_URL   as in scripts/bench-vs-pytorch.sh
#
# Requirements: bash, python3 (>= 3.9, with venv), network access on the first run (pip), cargo
# unless both binaries are given. Memory: PyTorch keeps the float64 graph (small, batch 2 at
# 256x256: 2.6 GB peak RSS). Not run in CI.
set -euo pipefail
cd "$(dirname "$0")/.."

CONFIGS=small
SIZE=200x136
BATCH=2
TOL=1e-4
SEED=0
THREADS=2
TOP=10
WORK=""
while [ $# -gt 0 ]; do
  case "$1" in
    --config|--configs) CONFIGS=$2; shift 2 ;;
    --size) SIZE=$2; shift 2 ;;
    --batch) BATCH=$2; shift 2 ;;
    --tol) TOL=$2; shift 2 ;;
    --seed) SEED=$2; shift 2 ;;
    --threads) THREADS=$2; shift 2 ;;
    --top) TOP=$2; shift 2 ;;
    --work) WORK=$2; shift 2 ;;
    -h|--help) sed -n '2,/^set -euo/p' "$0" | sed '$d; s/^# \{0,1\}//'; exit 0 ;;
    *) echo "unknown argument $1 (see --help)" >&2; exit 2 ;;
  esac
done

TORCH_PY=scripts/bench/pixl_torch.py
# shellcheck source=scripts/lib/torch-common.sh
. scripts/lib/torch-common.sh
torch_python
pixl_bin
if [ -z "${TRAIN_GRADS_BIN:-}" ]; then
  cargo build --release -q -p pixl-train --example train_grads
  TRAIN_GRADS_BIN=${CARGO_TARGET_DIR:-target}/release/examples/train_grads
fi
[ -x "$TRAIN_GRADS_BIN" ] || { echo "no train_grads binary at $TRAIN_GRADS_BIN" >&2; exit 1; }

if [ -z "$WORK" ]; then
  WORK=$(mktemp -d)
  trap 'rm -rf "$WORK"' EXIT
else
  mkdir -p "$WORK"
fi

echo "pixl: $PIXL_BIN ($("$PIXL_BIN" --version)); $TRAIN_GRADS_BIN" >&2
echo "torch: $("$PYTHON" -c 'import torch; print(torch.__version__)') ($PYTHON)" >&2

"$TRAIN_GRADS_BIN" --make-inputs --size "$SIZE" --batch "$BATCH" --seed "$SEED" --out "$WORK/inputs.safetensors"

FAILED=()
IFS=, read -r -a CONFIG_LIST <<< "$CONFIGS"
for cfg in "${CONFIG_LIST[@]}"; do
  echo "== $cfg: batch $BATCH at $SIZE, tol $TOL" >&2
  "$PIXL_BIN" -q model init --config "$cfg" --seed 0 --out "$WORK/$cfg-init.safetensors"
  "$PYTHON" "$TORCH_PY" perturb --weights "$WORK/$cfg-init.safetensors" --out "$WORK/$cfg.safetensors" --seed "$SEED" >&2
  rm -f "$WORK/$cfg-init.safetensors"
  RAYON_NUM_THREADS=$THREADS "$TRAIN_GRADS_BIN" --weights "$WORK/$cfg.safetensors" \
    --inputs "$WORK/inputs.safetensors" --out "$WORK/$cfg-grads-pixl.safetensors"
  OMP_NUM_THREADS=$THREADS MKL_NUM_THREADS=$THREADS "$PYTHON" "$TORCH_PY" grads --dtype f64 \
    --weights "$WORK/$cfg.safetensors" --inputs "$WORK/inputs.safetensors" \
    --out "$WORK/$cfg-grads-torch.safetensors" --threads "$THREADS" >&2
  if ! "$PYTHON" "$TORCH_PY" compare-grads "$WORK/$cfg-grads-pixl.safetensors" \
      "$WORK/$cfg-grads-torch.safetensors" --tol "$TOL" --top "$TOP"; then
    FAILED+=("$cfg")
  fi
done

if [ ${#FAILED[@]} -gt 0 ]; then
  echo "GRADIENT CHECK FAILED for: ${FAILED[*]}" >&2
  exit 1
fi
echo "gradient check passed for $CONFIGS (batch $BATCH at $SIZE, tol $TOL)" >&2
