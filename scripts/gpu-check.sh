#!/usr/bin/env bash
# Everything a GPU machine has to measure, in one call (a GPU is lent for minutes, not hours).
#
#   scripts/gpu-check.sh --bundle               # on any x86-64 Linux machine, no GPU needed: build
#                                               # pixl with CUDA (scripts/cuda-setup.sh) into
#                                               # target/gpu-bundle/pixl.gz, the one file to carry
#   scripts/gpu-check.sh OUT                    # on the GPU machine, from the repository root
#   scripts/gpu-check.sh OUT --device cpu --quick   # the dry run: the same steps on the CPU, small
#
# Options: --device cuda[:N]|cpu (default cuda), --pixl PATH (default target/gpu-bundle/pixl.gz, else
# target/cuda/release/pixl, else target/release/pixl), --quick (small sizes: a dry run in minutes).
#
# Steps (each one's JSON output, exit status, seconds and peak device memory go to
# OUT/results.json; the console to OUT/log.txt; a table for BENCHMARKS.md to OUT/summary.md):
#   doctor       pixl doctor --json (build, devices, driver)
#   parity       pixl bench parity: the network (small, 256², f32 and bf16) and the estimators'
#                fixture models on the device against the CPU (f32 rel. L2 < 1e-4, bf16 < 2e-2)
#   fwd-512, fwd-1024   pixl bench model --config paper --dtype bf16 (2 warm-ups + 5 runs)
#   fwd-512-f32  the same in f32
#   train-step   pixl bench train-step --config paper --size 512x512 --batch 8 --dtype bf16
#                (f32 master weights, AdamW), and train-step-ckpt with gradient checkpointing
#   train-cpu, train-dev   a 20-step run of the tiny network on a small synthetic set, on the CPU
#                and on the device: the losses must agree (relative difference < 1e-2)
# Peak device memory is sampled with nvidia-smi every 50 ms (null where there is none). Steps go
# on after a failure; the script exits 1 if any failed.
#
# CUDA libraries: found as scripts/lib/gpu-common.sh says (a PyTorch environment's nvidia-* wheels,
# /usr/local/cuda*/lib64).
set -uo pipefail
ROOT="$(cd "$(dirname "$0")/.." && pwd)"
cd "$ROOT"

if [ "${1:-}" = --bundle ]; then
  set -e
  scripts/cuda-setup.sh
  mkdir -p target/gpu-bundle
  # The binary holds candle's PTX and quantised-kernel SASS (about 85 MB stripped); compressed it
  # is about a third of that, small enough to travel with the working tree.
  cp target/cuda/release/pixl target/gpu-bundle/pixl
  strip target/gpu-bundle/pixl 2>/dev/null || true
  gzip -9 -f target/gpu-bundle/pixl
  ls -la target/gpu-bundle/
  echo "carry target/gpu-bundle; on the GPU machine: scripts/gpu-check.sh OUT"
  exit 0
fi
case "${1:-}" in
  "" | -h | --help) sed -n '2,12p' "$0"; exit 0 ;;
  -*) echo "gpu-check.sh: the first argument is the output folder" >&2; exit 2 ;;
esac
OUT="$1"; shift
DEVICE=cuda; PIXL=""; QUICK=0
while [ $# -gt 0 ]; do
  case "$1" in
    --device) DEVICE="$2"; shift 2 ;;
    --pixl) PIXL="$2"; shift 2 ;;
    --quick) QUICK=1; shift ;;
    *) echo "gpu-check.sh: unknown option $1" >&2; exit 2 ;;
  esac
done
mkdir -p "$OUT"; OUT="$(cd "$OUT" && pwd)"
WORK="$(mktemp -d)"; trap 'rm -rf "$WORK"' EXIT
exec > >(tee -a "$OUT/log.txt") 2>&1

# shellcheck source=scripts/lib/gpu-common.sh
. "$ROOT/scripts/lib/gpu-common.sh"
find_pixl "$ROOT" "$WORK" "$PIXL" || { echo "no pixl binary: run scripts/gpu-check.sh --bundle first, or pass --pixl"; exit 1; }
echo "gpu-check: $(date -u +%Y-%m-%dT%H:%M:%SZ), pixl $PIXL, device $DEVICE, quick $QUICK"
[[ "$DEVICE" == cuda* ]] && cuda_env "$WORK"

# ---- steps ----
RESULTS="$OUT/results.json"; echo "[" >"$RESULTS"; FIRST=1; FAILED=0
watch_start() {
  PEAK_FILE="$WORK/mem.$1"; WATCH_PID=""
  if command -v nvidia-smi >/dev/null 2>&1; then
    nvidia-smi --query-gpu=memory.used --format=csv,noheader,nounits -lms 50 >"$PEAK_FILE" 2>/dev/null &
    WATCH_PID=$!
  fi
}
watch_stop() {
  if [ -n "$WATCH_PID" ]; then
    kill "$WATCH_PID" 2>/dev/null; wait "$WATCH_PID" 2>/dev/null
    sort -n "$PEAK_FILE" | tail -1
  else
    echo null
  fi
}
# step NAME CMD...: runs CMD (its stdout is JSON), records it in results.json.
step() {
  local name="$1"; shift
  echo "== $name: $*"
  local t0=$SECONDS
  watch_start "$name"
  "$@" >"$WORK/$name.json"
  local rc=$?
  local peak; peak="$(watch_stop)"; [ -n "$peak" ] || peak=null
  local secs=$((SECONDS - t0))
  [ $rc -eq 0 ] || { FAILED=$((FAILED + 1)); echo "!! $name failed (exit $rc)"; }
  [ -s "$WORK/$name.json" ] || echo null >"$WORK/$name.json"
  cat "$WORK/$name.json"
  { [ $FIRST -eq 1 ] || echo ","; FIRST=0
    printf '{"step": "%s", "command": "%s", "exit": %d, "seconds": %d, "peak_device_mib": %s, "output":\n' \
      "$name" "${*//\"/\\\"}" "$rc" "$secs" "$peak"
    cat "$WORK/$name.json"; echo "}"; } >>"$RESULTS"
}

if [ $QUICK -eq 1 ]; then
  NET=tiny; S1=128x128; S2=192x192; BATCH=2; TS=128x128; PAR=small; PSIZE=128x128
else
  NET=paper; S1=512x512; S2=1024x1024; BATCH=8; TS=512x512; PAR=small; PSIZE=256x256
fi
step doctor "$PIXL" doctor --json
step parity "$PIXL" bench parity --device "$DEVICE" --config $PAR --size $PSIZE --fixtures "$ROOT/fixtures" --json
step fwd-512 "$PIXL" bench model --config $NET --size $S1 --dtype bf16 --device "$DEVICE" --warmups 2 --runs 5 --json
step fwd-1024 "$PIXL" bench model --config $NET --size $S2 --dtype bf16 --device "$DEVICE" --warmups 2 --runs 5 --json
step fwd-512-f32 "$PIXL" bench model --config $NET --size $S1 --dtype f32 --device "$DEVICE" --warmups 2 --runs 5 --json
step train-step "$PIXL" bench train-step --config $NET --size $TS --batch $BATCH --dtype bf16 --device "$DEVICE" --warmups 2 --runs 5 --json
step train-step-ckpt "$PIXL" bench train-step --config $NET --size $TS --batch $BATCH --dtype bf16 --checkpoint --device "$DEVICE" --warmups 2 --runs 5 --json

# A short run on the CPU and on the device from the same data, seed and config.
agreement_data "$PIXL" "$WORK/synth" || FAILED=$((FAILED + 1))
for tag in cpu dev; do
  dev=cpu; [ $tag = cpu ] || dev="$DEVICE"
  agreement_toml "$WORK/synth" "$WORK/run-$tag" >"$WORK/train-$tag.toml"
  step "train-$tag" "$PIXL" --quiet train --config "$WORK/train-$tag.toml" --device "$dev" --json
done
echo "]" >>"$RESULTS"
AGREE="$(loss_agreement "$WORK/run-cpu/log.jsonl" "$WORK/run-dev/log.jsonl")" || FAILED=$((FAILED + 1))
python3 - "$RESULTS" "$OUT/summary.md" "$DEVICE" "$AGREE" <<'EOF' || FAILED=$((FAILED + 1))
import json, sys
results, summary, device, agree = sys.argv[1:]
rows = {r["step"]: r for r in json.load(open(results))}
lines = [f"# gpu-check on {device}", "", "| step | result | peak device MiB | exit |", "|---|---|---|---|"]
for name, r in rows.items():
    o = r["output"] or {}
    if "timing" in o:
        t = o["timing"]
        res = f"median {t['median_ms']:.2f} ms, min {min(t['runs_ms'] or [float('nan')]):.2f} ms ({o.get('config')}, {o.get('width')}x{o.get('height')}, {o.get('dtype')}, batch {o.get('batch', 1)})"
    elif name == "parity":
        res = "; ".join(f"{x['what']} {x['dtype']}: {x['rel_l2']:.1e}" for x in o.get("rows", []))
    elif name.startswith("train-") and "final_loss" in o:
        res = f"final loss {o['final_loss']:.5f}"
    elif name == "doctor":
        c = o.get("cuda", {})
        res = f"driver {c.get('driver_version')}, devices {[d['name'] for d in c.get('devices', [])]}, unavailable: {c.get('unavailable')}"
    else:
        res = ""
    lines.append(f"| {name} | {res} | {r['peak_device_mib']} | {r['exit']} |")
lines += ["", agree]
open(summary, "w").write("\n".join(lines) + "\n")
print("\n".join(lines))
EOF
echo "gpu-check: $FAILED failed step(s); results in $OUT"
[ $FAILED -eq 0 ]
