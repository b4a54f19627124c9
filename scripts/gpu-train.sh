#!/usr/bin/env bash
# Minutes on a GPU become a better model: one call that makes training data on the machine's CPU
# cores while it trains on its GPU, and brings the weights back.
#
#   scripts/gpu-check.sh --bundle                  # first, on any x86-64 Linux machine (no GPU):
#                                                  # the CUDA pixl to carry, target/gpu-bundle/pixl.gz
#   scripts/gpu-train.sh OUT                       # on the GPU machine: about 9 minutes in all
#   scripts/gpu-train.sh OUT --init W.safetensors  # continue from the weights an earlier call returned
#   scripts/gpu-train.sh OUT --device cpu --quick  # the dry run: every step, small, on the CPU
#
# Options: --minutes M (training time; default 6, --quick 1.5), --init W (weights returned by an
# earlier call — one file, or the first of its parts — to continue from), --device cuda[:N]|cpu
# (default cuda), --quick (the tiny model, small images: a dry run), --seed S (first data seed;
# default: the clock, so every call adds new scenes), --workers N (pixl synth processes; default:
# all cores but two), --pixl PATH (default: as scripts/gpu-check.sh finds it).
#
# Steps (the console goes to OUT/log.txt):
#  1. check   pixl doctor --json, then a 20-step tiny run on the CPU and on the device from the same
#             data, whose losses must agree (relative difference < 1e-2); if not, the call stops
#             here, within about a minute, with the log.
#  2. data    pixl synth in the background, one process per core (RAYON_NUM_THREADS=1): first the
#             held-out set (seed 424242, never trained on), then chunks of photo-style scenes with
#             coarse-reconstruction C_T (albedo textured with the photo and estimated-style,
#             alternating), each chunk its own seed, into DATA/<seed>/. The trainer reads DATA again
#             every 25 steps (`[data] refresh_every`), so scenes join as they are finished.
#  3. train   pixl train --minutes M on the device: the model of assets/gpu-weights/model.toml
#             (--quick: assets/demo-weights/tiny-p8.toml), L1 with 0.8 of it after the evaluation's
#             scale correction ([loss] scale_corrected; assets/demo-weights/README.md), bf16 compute
#             with f32 master weights on CUDA, a checkpoint every 2 minutes, each exported at once
#             to OUT/weights/ as bf16 parts of at most 16 MiB (pixl weights split), so a call cut
#             short still returns its last one.
#  4. eval    pixl eval on the held-out set in the paper's inference setting (--ct coarse): the new
#             weights against the bundled ones (assets/demo-weights), identity, compose and
#             compose-camera, PSNR / SSIM and the light-response gain; OUT/sheet.png shows its first
#             pairs (source | C_T albedo, shading, residual | each method | target).
#
# What comes back in OUT (five files; with gpu-check's three, the eight a call may return):
# log.txt, summary.json (the held-out table, GPU step time and peak memory, "beats_bundled", and
# under "record" the config, data seeds, steps, device, wall time and losses that are kept beside
# bundled weights), sheet.png, weights/model-0000k-of-0000n.safetensors (two parts).
#
# Afterwards, on the development machine: commit the figures to BENCHMARKS.md, and if
# summary.json says "beats_bundled": true, the weights (pixl weights join OUT/weights/*.safetensors
# -o assets/gpu-weights/pixl-gpu.safetensors) with their record (python3 -c 'import json,sys;
# json.dump(json.load(open(sys.argv[1]))["record"], sys.stdout, indent=1)' OUT/summary.json >
# assets/gpu-weights/record.json). To continue that training on the next GPU, pass --init.
set -uo pipefail
ROOT="$(cd "$(dirname "$0")/.." && pwd)"
cd "$ROOT"

case "${1:-}" in
  "" | -h | --help) sed -n '2,/^set -uo pipefail/p' "$0" | sed '$d'; exit 0 ;;
  -*) echo "gpu-train.sh: the first argument is the output folder" >&2; exit 2 ;;
esac
OUT="$1"; shift
DEVICE=cuda; PIXL_GIVEN=""; QUICK=0; MINUTES=""; INIT=""; SEED=""; WORKERS=""
while [ $# -gt 0 ]; do
  case "$1" in
    --device) DEVICE="$2"; shift 2 ;;
    --pixl) PIXL_GIVEN="$2"; shift 2 ;;
    --quick) QUICK=1; shift ;;
    --minutes) MINUTES="$2"; shift 2 ;;
    --init) INIT="$2"; shift 2 ;;
    --seed) SEED="$2"; shift 2 ;;
    --workers) WORKERS="$2"; shift 2 ;;
    *) echo "gpu-train.sh: unknown option $1 (see --help)" >&2; exit 2 ;;
  esac
done
[ -n "$INIT" ] && { [ -f "$INIT" ] || { echo "gpu-train.sh: --init $INIT: no such file" >&2; exit 2; }; INIT="$(cd "$(dirname "$INIT")" && pwd)/$(basename "$INIT")"; }
INIT_GIVEN="$INIT"
mkdir -p "$OUT/weights"; OUT="$(cd "$OUT" && pwd)"
WORK="$(mktemp -d)"
PIDS=()
stop_background() {
  for p in "${PIDS[@]}"; do kill "$p" 2>/dev/null; done
  # the synth processes the workers started (they write under WORK/tmp-* and WORK/heldout.tmp)
  pkill -f -- "-o $WORK/" 2>/dev/null
  PIDS=()
}
cleanup() {
  stop_background
  rm -rf "$WORK"
}
trap cleanup EXIT
exec > >(tee -a "$OUT/log.txt") 2>&1
T0=$SECONDS
say() { echo "[$(date -u +%H:%M:%S) +$((SECONDS - T0))s] $*"; }

# shellcheck source=scripts/lib/gpu-common.sh
. "$ROOT/scripts/lib/gpu-common.sh"
find_pixl "$ROOT" "$WORK" "$PIXL_GIVEN" || { say "no pixl binary: run scripts/gpu-check.sh --bundle first, or pass --pixl"; exit 1; }
[[ "$DEVICE" == cuda* ]] && cuda_env "$WORK"
CORES="$(nproc)"
[ -n "$WORKERS" ] || WORKERS=$((CORES > 3 ? CORES - 2 : 1))
[ -n "$SEED" ] || SEED="$(date +%s)"
BUNDLED="$ROOT/assets/demo-weights/pixl-tiny-synth.safetensors"
if [ $QUICK -eq 1 ]; then
  MODEL="$ROOT/assets/demo-weights/tiny-p8.toml"; MINUTES="${MINUTES:-1.5}"
  SIZE=64; LIGHTS=3; SPP=4; CHUNK=1; BATCH=4; LONG=64; PRECISION=f32
  HELD_ARGS=(--scenes 2 --lights 2 --size 64 --spp 4)
  LR=1e-3; WARMUP=10
else
  MODEL="$ROOT/assets/gpu-weights/model.toml"; MINUTES="${MINUTES:-6}"
  SIZE=128; LIGHTS=4; SPP=16; CHUNK=1; BATCH=32; LONG=128; PRECISION=bf16
  HELD_ARGS=(--scenes 6 --lights 3 --size 128 --spp 16)
  LR=5e-4; WARMUP=200
fi
[ "$DEVICE" = cpu ] && PRECISION=f32
say "gpu-train: pixl $PIXL, device $DEVICE, quick $QUICK, $MINUTES min of training, $WORKERS synth workers on $CORES cores, data seeds from $SEED, init ${INIT:-none}"

# ---- 1. check ----
"$PIXL" doctor --json >"$WORK/doctor.json" || say "pixl doctor failed (exit $?)"
cat "$WORK/doctor.json"
agreement_data "$PIXL" "$WORK/agree-data" || { say "making the agreement check's data failed"; exit 1; }
for tag in cpu dev; do
  dev=cpu; [ $tag = cpu ] || dev="$DEVICE"
  agreement_toml "$WORK/agree-data" "$WORK/agree-$tag" >"$WORK/agree-$tag.toml"
  "$PIXL" --quiet train --config "$WORK/agree-$tag.toml" --device "$dev" --json >"$WORK/agree-$tag.json" \
    || { say "the 20-step run on $dev failed: stopping"; exit 1; }
done
AGREE="$(loss_agreement "$WORK/agree-cpu/log.jsonl" "$WORK/agree-dev/log.jsonl")" \
  || { say "$AGREE: the device does not compute what the CPU does; stopping"; exit 1; }
say "$AGREE"

# ---- 2. data ----
DATA="$WORK/data"; HELD="$WORK/heldout"; mkdir -p "$DATA" "$WORK/synth-logs"
synth_worker() {
  local w="$1" k=0 seed albedo
  if [ "$w" = 0 ]; then
    RAYON_NUM_THREADS=1 "$PIXL" --quiet synth "${HELD_ARGS[@]}" --seed 424242 --test-every 1 \
      --coarse --coarse-albedo photo -o "$WORK/heldout.tmp" >"$WORK/synth-logs/heldout.log" 2>&1 \
      && mv "$WORK/heldout.tmp" "$HELD"
  fi
  while :; do
    seed=$((SEED + k * WORKERS + w)); k=$((k + 1))
    albedo=photo; [ $((seed % 2)) = 1 ] && albedo=estimated
    # Written beside DATA and moved in when complete: the trainer sees only finished sets.
    RAYON_NUM_THREADS=1 "$PIXL" --quiet synth --scenes $CHUNK --lights $LIGHTS --size $SIZE --spp $SPP \
      --seed "$seed" --test-every 1000000 --coarse --coarse-albedo $albedo -o "$WORK/tmp-$seed" \
      >>"$WORK/synth-logs/$w.log" 2>&1 && mv "$WORK/tmp-$seed" "$DATA/$seed"
  done
}
for w in $(seq 0 $((WORKERS - 1))); do synth_worker "$w" & PIDS+=($!); done
# Training starts as soon as one chunk is there (the others follow every 25 steps).
while [ -z "$(ls -A "$DATA")" ]; do
  sleep 1
  [ $((SECONDS - T0)) -lt 900 ] || { say "no training data after 15 minutes: stopping"; exit 1; }
done
say "first data chunk ready; training"

# ---- 3. train ----
RUN="$WORK/run"
INIT_LINE=""
if [ -n "$INIT" ]; then
  if [[ "$INIT" =~ -0*1-of-[0-9]+\.safetensors$ ]]; then
    "$PIXL" --quiet weights join "$INIT" -o "$WORK/init.safetensors" || { say "joining --init's parts failed"; exit 1; }
    INIT="$WORK/init.safetensors"
  fi
  INIT_LINE="init_weights = \"$INIT\""
  WARMUP=$((WARMUP / 4 + 1))
fi
cat >"$WORK/train.toml" <<EOF
[model]
preset = "$MODEL"
init_seed = 0
$INIT_LINE

[data]
dataset = "synth:$DATA"
split = "train"
cache = true
refresh_every = 25

[data.sampler]
long_side = $LONG
multiple = 16
min_scale = 0.7
coarse_ct = 0.5
coarse_pair_share = 0.25

[optim]
batch_size = $BATCH
clip_norm = 1.0
precision = "$PRECISION"

[optim.schedule]
peak_lr = $LR
final_lr = $(python3 -c "print($LR / 10)")
warmup_steps = $WARMUP
total_steps = 100000000

[optim.adamw]
weight_decay = 0.05

[loss]
perceptual_weight = 0.0
scale_corrected = 0.8

[augment]
enabled = true

[run]
out_dir = "$RUN"
steps = 100000000
seed = $SEED
log_every = 5
sample_every = 100000000
checkpoint_every = 100000000
max_minutes = $MINUTES
checkpoint_minutes = 2.0
EOF
cat "$WORK/train.toml"
# Each checkpoint is exported to OUT/weights at once (the last survives a cut-off call).
export_weights() {
  "$PIXL" --quiet weights split "$RUN/model.safetensors" --dtype bf16 --max-part-mib 16 --force \
    -o "$OUT/weights" --json >"$WORK/split.json" && cp "$RUN/train.toml" "$WORK/last-export.toml" 2>/dev/null
}
(
  last=""
  while sleep 5; do
    m="$(stat -c %Y "$RUN/model.safetensors" 2>/dev/null)" || continue
    [ "$m" != "$last" ] && export_weights && last="$m" && echo "exported the checkpoint of $(date -u +%H:%M:%S)"
  done
) & PIDS+=($!)
MEM="$WORK/gpu-mem.csv"
if command -v nvidia-smi >/dev/null 2>&1 && [ "$DEVICE" != cpu ]; then
  nvidia-smi --query-gpu=memory.used,utilization.gpu --format=csv,noheader,nounits -lms 500 >"$MEM" 2>/dev/null & PIDS+=($!)
fi
TRAIN_T0=$SECONDS
"$PIXL" --quiet train --config "$WORK/train.toml" --device "$DEVICE" --json >"$WORK/train.json"
TRAIN_RC=$?
TRAIN_SECS=$((SECONDS - TRAIN_T0))
cat "$WORK/train.json"
say "training ended (exit $TRAIN_RC) after ${TRAIN_SECS}s"
# The data workers stop now (an unfinished chunk is dropped); the held-out set must be there.
for i in $(seq 1 120); do [ -d "$HELD" ] && break; sleep 1; done
stop_background
[ $TRAIN_RC -eq 0 ] && [ -f "$RUN/model.safetensors" ] || { say "training failed; see above"; exit 1; }
export_weights || { say "exporting the weights failed"; exit 1; }

# ---- 4. eval ----
[ -d "$HELD" ] || { say "the held-out set was not finished; no evaluation"; exit 1; }
cp "$RUN/model.safetensors" "$WORK/new.safetensors"
cp "$BUNDLED" "$WORK/bundled.safetensors"
"$PIXL" --quiet eval --dataset "synth:$HELD" --ct coarse \
  --weights "$WORK/new.safetensors" --weights "$WORK/bundled.safetensors" \
  --baselines identity,compose,compose-camera --runs 0 --device "$DEVICE" \
  --sheet "$OUT/sheet.png" --sheet-pairs 4 --out "$WORK/eval" --json >"$WORK/eval.json" \
  || { say "evaluation failed"; exit 1; }
cat "$WORK/eval/results.md"

# ---- summary ----
python3 - "$WORK" "$OUT" "$DEVICE" "$SEED" "$MINUTES" "$TRAIN_SECS" "$SECONDS" "$AGREE" "$MODEL" "$INIT_GIVEN" "$BATCH" <<'EOF'
import glob, json, os, statistics, sys
work, out, device, seed, minutes, train_secs, wall, agree, model, init, batch = sys.argv[1:]
load = lambda p, d=None: json.load(open(p)) if os.path.exists(p) else d
train, ev, doctor = load(f"{work}/train.json", {}), load(f"{work}/eval.json", {}), load(f"{work}/doctor.json", {})
log = [json.loads(l) for l in open(f"{work}/run/log.jsonl")]
steps = [r for r in log if "loss" in r]
step_ms = [1000 * int(batch) / r["images_per_s"] for r in steps[len(steps) // 5:] if r.get("images_per_s")]
mem = []
if os.path.exists(f"{work}/gpu-mem.csv"):
    for line in open(f"{work}/gpu-mem.csv"):
        try:
            mem.append([float(x) for x in line.split(",")])
        except ValueError:
            pass
chunks = sorted(os.listdir(f"{work}/data"))
every = max(1, len(steps) // 100)
record = {
    "model_config": model, "init": init or None, "device": device,
    "doctor_cuda": doctor.get("cuda"),
    "data": {"chunks": len(chunks), "seeds": f"{min(map(int, chunks), default='-')}..{max(map(int, chunks), default='-')} "
             f"(pixl synth --seed S per chunk, from {seed})", "scenes": train.get("scenes"), "heldout_seed": 424242},
    "steps": train.get("step"), "stopped_by": train.get("stopped_by"),
    "minutes": float(minutes), "train_seconds": int(train_secs), "wall_seconds": int(wall),
    "step_ms_median": statistics.median(step_ms) if step_ms else None, "batch": int(batch),
    "losses": [[r["step"], round(r["loss"], 5)] for r in steps[::every]],
    "final_loss": train.get("final_loss"),
    "train_toml": open(f"{work}/train.toml").read(),
}
methods = {m["method"]: m for m in ev.get("methods", [])}
resp = {r["method"]: r for r in ev.get("response", [])}
new, old = "Ours (new)", "Ours (bundled)"
def better(a, b):
    return a in methods and b in methods and methods[a]["psnr"] > methods[b]["psnr"] and \
        (a not in resp or b not in resp or resp[a]["gain"] > resp[b]["gain"])
summary = {
    "agreement": agree, "record": record,
    "gpu_peak_mib": max((m[0] for m in mem), default=None),
    "gpu_util_mean": statistics.mean(m[1] for m in mem) if mem else None,
    "heldout": {"dataset": ev.get("dataset"), "pairs": ev.get("pairs"),
                "rows": [{"method": k, "psnr": m["psnr"], "ssim": m["ssim"],
                          "gain": resp.get(k, {}).get("gain"), "correlation": resp.get(k, {}).get("correlation")}
                         for k, m in methods.items()]},
    "sheet_columns": ev.get("sheet_columns"),
    "beats_bundled": better(new, old),
}
json.dump(summary, open(f"{out}/summary.json", "w"), indent=1)
print(f"| method | PSNR | SSIM | light-response gain |\n|---|---:|---:|---:|")
for r in summary["heldout"]["rows"]:
    g = "" if r["gain"] is None else f"{r['gain']:.2f}"
    print(f"| {r['method']} | {r['psnr']:.2f} | {r['ssim']:.3f} | {g} |")
print(f"steps {record['steps']} in {train_secs} s ({record['step_ms_median']} ms/step median, batch {batch}), "
      f"GPU peak {summary['gpu_peak_mib']} MiB, {record['data']['chunks']} data chunks; beats the bundled weights: {summary['beats_bundled']}")
EOF
say "gpu-train: done; results in $OUT"
ls -la "$OUT" "$OUT/weights"
