#!/usr/bin/env bash
# The PIXLRelight network, `pixl` (candle) vs an independent PyTorch implementation
# (scripts/bench/pixl_torch.py), f32 on the CPU, same weights, same inputs, same thread count.
#
# For each config it:
#   1. writes fresh weights (`pixl model init`) and perturbs every tensor with seeded noise
#      (`pixl_torch.py perturb`), so that every part of the network, the zero-initialised modulation
#      conv included, affects the output;
#   2. checks parity: `pixl relight --source --intrinsics` and `pixl_torch.py parity` on the same
#      random source and C_T (EXR, --parity-size, not a multiple of 16 by default, so the edge
#      padding and the position-embedding resize are exercised); stops with an error if the max
#      absolute difference is above --tol;
#   3. times both in alternation, one process per side and round (pixl, torch, pixl, torch, ...),
#      each with the protocol of `pixl bench model` (--warmups untimed, then --runs timed forward
#      passes on uniform random inputs; model construction not timed);
# and prints a table: per-round medians of each side, the median of those and the fastest single
# run, the ratio pixl/torch of the medians, and the peak RSS of each process (max over rounds,
# whole process: for torch that includes the interpreter and libtorch).
#
# `pixl bench model` times its own seed-0 random weights of the config; torch times the perturbed
# checkpoint whose parity was just checked. Weight values do not change the work done.
#
# usage: scripts/bench-vs-pytorch.sh [--configs tiny,small,paper] [--size WxH] [--threads T]
#                                    [--rounds N] [--warmups W] [--runs R]
#                                    [--parity-size WxH] [--tol X] [--parity-only] [--int8]
#                                    [--work DIR]
#   --configs      comma-separated presets (default small)
#   --size         timed input size WIDTHxHEIGHT (default 512x512)
#   --threads      threads for both: RAYON_NUM_THREADS for pixl, torch.set_num_threads (and
#                  OMP_NUM_THREADS) for torch (default 2)
#   --rounds       processes per side, alternating (default 3)
#   --warmups/--runs  per process (default 2 / 5, as `pixl bench model`)
#   --parity-size  size of the parity check (default 200x136)
#   --tol          parity tolerance on the max abs difference (default 1e-4)
#   --parity-only  steps 1 and 2 only (no timing, no table)
#   --int8         time both sides with 8-bit linear layers: `pixl bench model --int8` (AVX-512
#                  VNNI; layers with >= 128 inputs) against PyTorch's dynamic quantization of
#                  every nn.Linear (`torch.ao.quantization.quantize_dynamic`, qint8); parity is
#                  still checked in f32
#   --work         folder for weights, inputs and outputs (default: a temporary folder, removed)
# env:
#   PIXL_BIN          a pixl binary to use; else `cargo build --release -p pixl-cli` is run
#   PYTHON            a Python to use as is (torch, safetensors, numpy, openexr are installed into
#                     it if missing); else a venv at PIXL_TORCH_VENV (default
#                     $HOME/.cache/pixl/venv-torch) is created on first use
#   TORCH_INDEX_URL   a package index for torch, e.g. https://download.pytorch.org/whl/cpu for the
#                     CPU-only wheels (default: PyPI, whose wheel pulls ~3 GB of CUDA libraries but
#                     runs on the CPU)
#
# Requirements: bash, python3 (>= 3.9, with venv), network access on the first run (pip), cargo
# unless PIXL_BIN is given. Disk: two checkpoints per config (paper: 2 × 2.9 GB). Not run in CI.
set -euo pipefail
cd "$(dirname "$0")/.."

CONFIGS=small
SIZE=512x512
THREADS=2
ROUNDS=3
WARMUPS=2
RUNS=5
PARITY_SIZE=200x136
TOL=1e-4
WORK=""
PARITY_ONLY=""
INT8=""
while [ $# -gt 0 ]; do
  case "$1" in
    --configs) CONFIGS=$2; shift 2 ;;
    --size) SIZE=$2; shift 2 ;;
    --threads) THREADS=$2; shift 2 ;;
    --rounds) ROUNDS=$2; shift 2 ;;
    --warmups) WARMUPS=$2; shift 2 ;;
    --runs) RUNS=$2; shift 2 ;;
    --parity-size) PARITY_SIZE=$2; shift 2 ;;
    --tol) TOL=$2; shift 2 ;;
    --parity-only) PARITY_ONLY=1; shift ;;
    --int8) INT8=--int8; shift ;;
    --work) WORK=$2; shift 2 ;;
    -h|--help) sed -n '2,/^set -euo/p' "$0" | sed '$d; s/^# \{0,1\}//'; exit 0 ;;
    *) echo "unknown argument $1 (see --help)" >&2; exit 2 ;;
  esac
done

TORCH_PY=scripts/bench/pixl_torch.py

# --- Python with torch ---------------------------------------------------------------------------
if [ -z "${PYTHON:-}" ]; then
  VENV=${PIXL_TORCH_VENV:-$HOME/.cache/pixl/venv-torch}
  if [ ! -x "$VENV/bin/python" ]; then
    echo "creating a venv at $VENV" >&2
    mkdir -p "$(dirname "$VENV")"
    python3 -m venv "$VENV"
  fi
  PYTHON=$VENV/bin/python
fi
if ! "$PYTHON" -c "import torch, safetensors, numpy, OpenEXR" 2>/dev/null; then
  echo "installing torch, safetensors, numpy, openexr into $("$PYTHON" -c 'import sys; print(sys.prefix)')" >&2
  "$PYTHON" -m pip install -q --upgrade pip
  "$PYTHON" -c "import torch" 2>/dev/null ||
    if [ -n "${TORCH_INDEX_URL:-}" ]; then
      "$PYTHON" -m pip install -q torch --index-url "$TORCH_INDEX_URL"
    else
      "$PYTHON" -m pip install -q torch
    fi
  "$PYTHON" -m pip install -q safetensors numpy openexr
fi

# --- pixl ----------------------------------------------------------------------------------------
if [ -z "${PIXL_BIN:-}" ]; then
  cargo build --release -q -p pixl-cli
  PIXL_BIN=${CARGO_TARGET_DIR:-target}/release/pixl
fi
[ -x "$PIXL_BIN" ] || { echo "no pixl binary at $PIXL_BIN" >&2; exit 1; }

if [ -z "$WORK" ]; then
  WORK=$(mktemp -d)
  trap 'rm -rf "$WORK"' EXIT
else
  mkdir -p "$WORK"
fi

# Runs a command and writes its peak RSS (MB) to the file $1 (no /usr/bin/time needed).
with_rss() {
  local out=$1; shift
  "$PYTHON" -c '
import resource, subprocess, sys
rc = subprocess.run(sys.argv[2:]).returncode
with open(sys.argv[1], "w") as f:
    f.write("%.1f" % (resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024.0))
sys.exit(rc)' "$out" "$@"
}

echo "pixl: $PIXL_BIN ($("$PIXL_BIN" --version))" >&2
echo "torch: $("$PYTHON" -c 'import torch; print(torch.__version__)') ($PYTHON)" >&2
echo "threads $THREADS, size $SIZE, $ROUNDS rounds of $WARMUPS warm-ups + $RUNS runs per process" >&2

"$PYTHON" "$TORCH_PY" inputs --size "$PARITY_SIZE" --seed 1 \
  --source "$WORK/src.exr" --intrinsics "$WORK/ct.exr" >&2

IFS=, read -r -a CONFIG_LIST <<< "$CONFIGS"
for cfg in "${CONFIG_LIST[@]}"; do
  echo "== $cfg" >&2
  "$PIXL_BIN" -q model init --config "$cfg" --seed 0 --out "$WORK/$cfg-init.safetensors"
  "$PYTHON" "$TORCH_PY" perturb --weights "$WORK/$cfg-init.safetensors" --out "$WORK/$cfg.safetensors" --seed 0 >&2
  rm -f "$WORK/$cfg-init.safetensors"

  # Parity first: no timing of a network that computes something else.
  RAYON_NUM_THREADS=$THREADS "$PIXL_BIN" -q relight --source "$WORK/src.exr" --intrinsics "$WORK/ct.exr" \
    --weights "$WORK/$cfg.safetensors" --out "$WORK/$cfg-pixl.exr"
  if ! "$PYTHON" "$TORCH_PY" parity --weights "$WORK/$cfg.safetensors" --source "$WORK/src.exr" \
      --intrinsics "$WORK/ct.exr" --reference "$WORK/$cfg-pixl.exr" --tol "$TOL" --threads "$THREADS" >&2; then
    echo "PARITY FAILED for $cfg: pixl and the PyTorch implementation disagree; not timing" >&2
    exit 1
  fi
  if [ -n "$PARITY_ONLY" ]; then
    rm -f "$WORK/$cfg.safetensors"
    continue
  fi

  for r in $(seq 1 "$ROUNDS"); do
    echo "   round $r/$ROUNDS: pixl" >&2
    RAYON_NUM_THREADS=$THREADS with_rss "$WORK/$cfg-pixl-$r.rss" \
      "$PIXL_BIN" -q bench model --config "$cfg" --size "$SIZE" --dtype f32 $INT8 \
      --warmups "$WARMUPS" --runs "$RUNS" --json > "$WORK/$cfg-pixl-$r.json"
    echo "   round $r/$ROUNDS: torch" >&2
    OMP_NUM_THREADS=$THREADS MKL_NUM_THREADS=$THREADS with_rss "$WORK/$cfg-torch-$r.rss" \
      "$PYTHON" "$TORCH_PY" time --weights "$WORK/$cfg.safetensors" --size "$SIZE" --threads "$THREADS" $INT8 \
      --warmups "$WARMUPS" --runs "$RUNS" --json > "$WORK/$cfg-torch-$r.json"
  done
  rm -f "$WORK/$cfg.safetensors"
done

[ -n "$PARITY_ONLY" ] && { echo "parity passed for $CONFIGS" >&2; exit 0; }

# --- table ---------------------------------------------------------------------------------------
"$PYTHON" - "$WORK" "$SIZE" "$ROUNDS" "${CONFIG_LIST[@]}" <<'PY'
import json, statistics, sys
from pathlib import Path

work, size, rounds, configs = Path(sys.argv[1]), sys.argv[2], int(sys.argv[3]), sys.argv[4:]

def side(cfg, name):
    medians, runs, rss = [], [], []
    for r in range(1, rounds + 1):
        j = json.loads((work / f"{cfg}-{name}-{r}.json").read_text())
        t = j.get("timing", j)  # pixl nests its timing; pixl_torch.py does not
        medians.append(t["median_ms"])
        runs += t["runs_ms"]
        rss.append(float((work / f"{cfg}-{name}-{r}.rss").read_text()))
    return medians, statistics.median(medians), min(runs), max(rss)

fmt = lambda xs: " ".join(f"{x:.0f}" for x in xs)
head = ["config", "size", "pixl rounds (ms)", "torch rounds (ms)", "pixl med", "pixl min",
        "torch med", "torch min", "pixl/torch", "pixl RSS MB", "torch RSS MB"]
rows = []
for cfg in configs:
    pr, pm, pmin, prss = side(cfg, "pixl")
    tr, tm, tmin, trss = side(cfg, "torch")
    rows.append([cfg, size, fmt(pr), fmt(tr), f"{pm:.1f}", f"{pmin:.1f}", f"{tm:.1f}", f"{tmin:.1f}",
                 f"{pm / tm:.2f}", f"{prss:.0f}", f"{trss:.0f}"])
print("| " + " | ".join(head) + " |")
print("|" + "|".join("---" for _ in head) + "|")
for r in rows:
    print("| " + " | ".join(r) + " |")
PY
