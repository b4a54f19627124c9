#!/usr/bin/env bash
# One PIXLRelight training step, `pixl` (candle) vs an independent PyTorch implementation
# (scripts/bench/pixl_torch.py), f32 on the CPU, same thread count.
#
# The step is `pixl bench train-step`'s: forward on random src (B, 3, H, W) and C_T (B, 9, H, W),
# the L1 loss against a random target (loss.rs: mean absolute error of the clipped output), the
# backward pass, clipping of the gradients by their global norm at 1, and one AdamW update
# (lr 1e-4, betas (0.9, 0.95), eps 1e-8, weight decay 0.05 on the tensors optim.rs `decays`
# selects). PyTorch runs the same: `forward_unclipped`, the same loss, `loss.backward()`,
# `torch.nn.utils.clip_grad_norm_(…, 1.0)`, `torch.optim.AdamW` with two parameter groups
# (decayed or not, by the same rule) and the same hyper-parameters. That both compute the same
# gradients is checked by scripts/check-train-grads.sh, not here.
#
# For each config it:
#   1. writes fresh weights (`pixl model init`), perturbed with seeded noise (`pixl_torch.py
#      perturb`, as scripts/bench-vs-pytorch.sh) for the PyTorch side, which loads them with
#      strict names and shapes; the PyTorch parameter count must equal pixl's;
#   2. times both in alternation, one process per side and round (pixl, torch, pixl, torch, ...),
#      each with the protocol of `pixl bench train-step` (--warmups untimed steps, then --runs
#      timed steps; model construction not timed; per-step wall time, each step a full forward,
#      backward, clip and update);
# and prints markdown tables: per-round medians of each side, the median of those and the
# fastest single step, the ratio pixl/torch of the medians, the peak RSS of each process (max
# over rounds, whole process: for torch that includes the interpreter and libtorch); then
# PyTorch's forward (+ loss) / backward / clip + AdamW split (median over rounds of each
# process's medians) and the last loss of each side.
#
# `pixl bench train-step` trains its own seed-0 weights of the config (the modulation conv zero);
# torch trains the perturbed checkpoint. Weight values do not change the work done.
#
# usage: scripts/bench-train-vs-pytorch.sh [--configs SPEC,SPEC,...] [--size WxH] [--batch B]
#                                          [--threads T] [--rounds N] [--warmups W] [--runs R]
#                                          [--torch-adamw default|foreach|fused] [--work DIR]
#   --configs   comma-separated specs CONFIG[:WxH[:B]]: a preset (tiny, small, paper), optionally
#               with its own crop size and batch (default small,tiny:96x96:4; tiny:96x96:4 is
#               the bundled recipe's setting, assets/demo-weights/train.toml: batch_size 4,
#               long_side 96, whose largest crop is 96x96)
#   --size      crop WIDTHxHEIGHT for specs without one (default 256x256)
#   --batch     images per step for specs without one (default 2)
#   --threads   threads for both: RAYON_NUM_THREADS for pixl, torch.set_num_threads (and
#               OMP_NUM_THREADS) for torch (default 2)
#   --rounds    processes per side, alternating (default 3)
#   --warmups/--runs  steps per process (default 1 / 3)
#   --torch-adamw     torch.optim.AdamW implementation (default: PyTorch's own choice, a
#                     per-tensor loop on the CPU; foreach or fused for the multi-tensor kernels)
#   --work      folder for weights and results (default: a temporary folder, removed)
# env:
#   PIXL_BIN          a pixl binary to use; else `cargo build --release -p pixl-cli` is run
#   PYTHON            a Python to use as is (torch, safetensors, numpy, openexr are installed into
#                     it if missing); else a venv at PIXL_TORCH_VENV (default
#                     $HOME/.cache/pixl/venv-torch) is created on first use
#   TORCH_INDEX_URL   a package index for torch, e.g. https://download.pytorch.org/whl/cpu
#
# Requirements: bash, python3 (>= 3.9, with venv), network access on the first run (pip), cargo
# unless PIXL_BIN is given. Memory: both keep the whole forward graph (small, batch 2 at 256x256:
# a few GB per side). Not run in CI.
set -euo pipefail
cd "$(dirname "$0")/.."

CONFIGS=small,tiny:96x96:4
SIZE=256x256
BATCH=2
THREADS=2
ROUNDS=3
WARMUPS=1
RUNS=3
TORCH_ADAMW=default
WORK=""
while [ $# -gt 0 ]; do
  case "$1" in
    --configs|--config) CONFIGS=$2; shift 2 ;;
    --size) SIZE=$2; shift 2 ;;
    --batch) BATCH=$2; shift 2 ;;
    --threads) THREADS=$2; shift 2 ;;
    --rounds) ROUNDS=$2; shift 2 ;;
    --warmups) WARMUPS=$2; shift 2 ;;
    --runs) RUNS=$2; shift 2 ;;
    --torch-adamw) TORCH_ADAMW=$2; shift 2 ;;
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

if [ -z "$WORK" ]; then
  WORK=$(mktemp -d)
  trap 'rm -rf "$WORK"' EXIT
else
  mkdir -p "$WORK"
fi

echo "pixl: $PIXL_BIN ($("$PIXL_BIN" --version))" >&2
echo "torch: $("$PYTHON" -c 'import torch; print(torch.__version__)') ($PYTHON), AdamW $TORCH_ADAMW" >&2
echo "threads $THREADS, $ROUNDS rounds of $WARMUPS warm-ups + $RUNS steps per process" >&2

IFS=, read -r -a SPECS <<< "$CONFIGS"
KEYS=()
for spec in "${SPECS[@]}"; do
  IFS=: read -r cfg size batch <<< "$spec"
  size=${size:-$SIZE}
  batch=${batch:-$BATCH}
  [[ $size =~ ^[0-9]+x[0-9]+$ && $batch =~ ^[0-9]+$ ]] || { echo "bad spec $spec (CONFIG[:WxH[:B]])" >&2; exit 2; }
  key="$cfg-$size-b$batch"
  KEYS+=("$key")
  echo "== $cfg: batch $batch at $size" >&2
  "$PIXL_BIN" -q model init --config "$cfg" --seed 0 --out "$WORK/$key-init.safetensors"
  "$PYTHON" "$TORCH_PY" perturb --weights "$WORK/$key-init.safetensors" --out "$WORK/$key.safetensors" --seed 0 >&2
  rm -f "$WORK/$key-init.safetensors"
  for r in $(seq 1 "$ROUNDS"); do
    echo "   round $r/$ROUNDS: pixl" >&2
    RAYON_NUM_THREADS=$THREADS with_rss "$WORK/$key-pixl-$r.rss" \
      "$PIXL_BIN" -q bench train-step --config "$cfg" --size "$size" --batch "$batch" --dtype f32 \
      --warmups "$WARMUPS" --runs "$RUNS" --json > "$WORK/$key-pixl-$r.json"
    echo "   round $r/$ROUNDS: torch" >&2
    OMP_NUM_THREADS=$THREADS MKL_NUM_THREADS=$THREADS with_rss "$WORK/$key-torch-$r.rss" \
      "$PYTHON" "$TORCH_PY" train-step --weights "$WORK/$key.safetensors" --size "$size" --batch "$batch" \
      --threads "$THREADS" --adamw "$TORCH_ADAMW" --warmups "$WARMUPS" --runs "$RUNS" --json \
      > "$WORK/$key-torch-$r.json"
  done
  rm -f "$WORK/$key.safetensors"
done

# --- tables --------------------------------------------------------------------------------------
"$PYTHON" - "$WORK" "$ROUNDS" "$THREADS" "${KEYS[@]}" <<'PY'
import json, statistics, sys
from pathlib import Path

work, rounds, threads, keys = Path(sys.argv[1]), int(sys.argv[2]), sys.argv[3], sys.argv[4:]
med = statistics.median

def load(key, name):
    return [json.loads((work / f"{key}-{name}-{r}.json").read_text()) for r in range(1, rounds + 1)]

def side(js, key, name):
    medians, runs = [], []
    for j in js:
        t = j.get("timing", j)  # pixl nests its timing; pixl_torch.py does not
        medians.append(t["median_ms"])
        runs += t["runs_ms"]
    rss = max(float((work / f"{key}-{name}-{r}.rss").read_text()) for r in range(1, rounds + 1))
    return medians, med(medians), min(runs), rss

fmt = lambda xs: " ".join(f"{x:.0f}" for x in xs)
head = ["config", "crop", "batch", "params", "pixl rounds (ms)", "torch rounds (ms)", "pixl med", "pixl min",
        "torch med", "torch min", "pixl/torch", "pixl RSS MB", "torch RSS MB"]
rows, split_rows, bad = [], [], []
for key in keys:
    pj, tj = load(key, "pixl"), load(key, "torch")
    p0, t0 = pj[0], tj[0]
    if p0["params"] != t0["params"]:
        bad.append(f"{key}: pixl has {p0['params']} parameters, the PyTorch twin {t0['params']}")
    pr, pm, pmin, prss = side(pj, key, "pixl")
    tr, tm, tmin, trss = side(tj, key, "torch")
    size = f"{p0['width']}x{p0['height']}"
    rows.append([p0["config"], size, str(p0["batch"]), f"{p0['params'] / 1e6:.2f} M", fmt(pr), fmt(tr),
                 f"{pm:.1f}", f"{pmin:.1f}", f"{tm:.1f}", f"{tmin:.1f}", f"{pm / tm:.2f}", f"{prss:.0f}", f"{trss:.0f}"])
    sp = {k: med([j["split_median_ms"][k] for j in tj]) for k in ("forward", "backward", "clip_optim")}
    split_rows.append([p0["config"], size, str(p0["batch"]), f"{sp['forward']:.1f}", f"{sp['backward']:.1f}",
                       f"{sp['clip_optim']:.1f}", f"{tm:.1f}", f"{p0['last_loss']:.4f}", f"{tj[-1]['last_loss']:.4f}"])

def table(head, rows):
    print("| " + " | ".join(head) + " |")
    print("|" + "|".join("---" for _ in head) + "|")
    for r in rows:
        print("| " + " | ".join(r) + " |")

print(f"Training step (forward, backward, global-norm clip, AdamW), f32, CPU, {threads} threads; "
      f"ms per step; rounds (processes per side): {rounds}")
print()
table(head, rows)
print()
print("PyTorch's split (medians, ms) and the last loss of each side (different weights: pixl trains "
      "its seed-0 init, torch the perturbed checkpoint)")
print()
table(["config", "crop", "batch", "torch forward + loss", "torch backward", "torch clip + AdamW", "torch step",
       "pixl last loss", "torch last loss"], split_rows)
for line in bad:
    print(f"PARAMETER COUNT MISMATCH {line}", file=sys.stderr)
sys.exit(1 if bad else 0)
PY
