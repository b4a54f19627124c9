# Shared by scripts/gpu-check.sh and scripts/gpu-train.sh (sourced, not run): finding the `pixl`
# binary to use on a GPU machine and the CUDA libraries it opens.
#
#   find_pixl ROOT WORK [PATH]   sets PIXL: PATH if given, else target/gpu-bundle/pixl.gz (the
#                                bundle built by `scripts/gpu-check.sh --bundle`, unpacked into
#                                WORK), else target/cuda/release/pixl, target/release/pixl,
#                                target/debug/pixl; returns 1 if there is none
#   cuda_env WORK                adds the CUDA libraries' folders to LD_LIBRARY_PATH (below)
#
# CUDA libraries: the binary opens libcuda.so.1, libcublas.so.13, libcublasLt.so.13 and
# libcurand.so.10 at run time. cuda_env adds the folders of a Python environment's `nvidia-*`
# wheels (PyTorch's) and /usr/local/nvidia/lib64, /usr/local/cuda*/lib64 to LD_LIBRARY_PATH, and
# points the unversioned names cudarc tries first at those libraries (links under WORK/libpin).

find_pixl() {
  local root="$1" work="$2" given="${3:-}" p
  PIXL=""
  if [ -n "$given" ]; then
    PIXL="$given"
  elif [ -f "$root/target/gpu-bundle/pixl.gz" ]; then
    gzip -dc "$root/target/gpu-bundle/pixl.gz" >"$work/pixl" && chmod +x "$work/pixl" && PIXL="$work/pixl"
  fi
  if [ -z "$PIXL" ]; then
    for p in target/cuda/release/pixl target/release/pixl target/debug/pixl; do
      if [ -x "$root/$p" ]; then PIXL="$root/$p"; break; fi
    done
  fi
  [ -n "$PIXL" ] && [ -x "$PIXL" ]
}

cuda_env() {
  local work="$1" dirs="" py found d lib pin
  for py in python3 /opt/torch/.venv/bin/python3; do
    command -v "$py" >/dev/null 2>&1 || continue
    found="$("$py" - <<'PYEOF' 2>/dev/null
import glob, os, site
roots = site.getsitepackages() + [site.getusersitepackages()]
print(":".join(sorted({d for r in roots for d in glob.glob(os.path.join(r, "nvidia", "*", "lib"))})))
PYEOF
)"
    [ -n "$found" ] && dirs="$dirs:$found"
  done
  for d in /usr/local/nvidia/lib64 /usr/local/cuda*/lib64; do [ -d "$d" ] && dirs="$dirs:$d"; done
  pin="$work/libpin"; mkdir -p "$pin"
  local all
  IFS=: read -ra all <<<"$dirs"
  for lib in cublas.so.13 cublasLt.so.13 curand.so.10; do
    for d in "${all[@]}"; do
      if [ -n "$d" ] && [ -e "$d/lib$lib" ]; then ln -sf "$d/lib$lib" "$pin/lib${lib%%.so.*}.so"; break; fi
    done
  done
  export LD_LIBRARY_PATH="$pin$dirs${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
  echo "LD_LIBRARY_PATH=$LD_LIBRARY_PATH"
  command -v nvidia-smi >/dev/null && nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv
  return 0
}

# agreement_toml DATA RUN: the train.toml of the 20-step tiny run that is made on the CPU and on
# the device from the same data, seed and config (their losses must agree; see loss_agreement).
agreement_toml() {
  cat <<TOMLEOF
[model]
preset = "tiny"
init_seed = 0
[data]
dataset = "synth:$1"
[data.sampler]
long_side = 64
multiple = 16
[optim]
batch_size = 2
[optim.schedule]
peak_lr = 1e-3
warmup_steps = 5
total_steps = 20
[loss]
perceptual_weight = 0.0
[run]
out_dir = "$2"
steps = 20
seed = 0
log_every = 1
sample_every = 1000
checkpoint_every = 1000
TOMLEOF
}

# agreement_data PIXL DIR: the small synthetic set those two runs read.
agreement_data() {
  "$1" --quiet synth --scenes 4 --lights 2 --size 64 --spp 4 --seed 3 --test-every 1000 -o "$2"
}

# loss_agreement CPU_LOG DEV_LOG: compares the two runs' log.jsonl losses; prints one line and
# succeeds when both have the same number of steps (> 0) and every relative difference is < 1e-2.
loss_agreement() {
  python3 - "$1" "$2" <<'PYEOF'
import json, sys
def losses(p):
    try:
        return [r["loss"] for r in map(json.loads, open(p)) if "loss" in r]
    except OSError:
        return []
a, b = losses(sys.argv[1]), losses(sys.argv[2])
worst = max((abs(x - y) / max(abs(x), 1e-12) for x, y in zip(a, b)), default=float("inf"))
ok = len(a) == len(b) > 0 and worst < 1e-2
print(f"20-step loss curves, CPU vs device: {len(a)} and {len(b)} steps, worst relative difference {worst:.2e} ({'ok' if ok else 'FAILED'}, tolerance 1e-2)")
sys.exit(0 if ok else 1)
PYEOF
}
