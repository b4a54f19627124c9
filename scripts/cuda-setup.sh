#!/usr/bin/env bash
# Builds `pixl` with the `cuda` feature on a machine without a GPU or a system CUDA toolkit.
#
#   scripts/cuda-setup.sh                 # release build: target/cuda/release/pixl
#   scripts/cuda-setup.sh --ci            # what CI runs: debug build of every target with the
#                                         # feature, then the CPU tests of that build
#   scripts/cuda-setup.sh --env           # print the environment a cuda cargo command needs
#
# How it works, and why each step is needed:
# - nvcc, headers and the static CUDA runtime come from PyPI's CUDA **13.0** wheels, unpacked once
#   under $PIXL_CUDA13 (default ~/.cache/pixl/cuda13; kept between runs on the same machine).
#   13.0 and not newer: a CUDA 13.0 (R580) driver JIT-compiles PTX up to ISA 9.0 only, and newer
#   nvcc emits newer PTX.
# - candle-core 0.11.1 asks cudarc for `dynamic-linking`, which links libcuda/libcublas at build
#   time and makes the binary refuse to start where they are missing. We build against a copy of
#   candle-core whose only change is that feature switched to `dynamic-loading` (made from the
#   crate in cargo's registry cache, under target/cuda-patch/), given to cargo as a
#   `[patch.crates-io]` on the command line. The binary then starts anywhere and opens libcuda /
#   libcublas when a CUDA device is first asked for; without them it says "no CUDA device".
#   The patch changes Cargo.lock's entry for candle-core, so the lock file is restored afterwards.
# - cudarc is built for CUDA 13.0 (CUDARC_CUDA_VERSION=13000), so at run time it looks for the
#   `.so.13` libraries (driver R580 or newer, cuBLAS 13 on LD_LIBRARY_PATH).
# - Kernels are compiled for Hopper (CUDA_COMPUTE_CAP=90, i.e. H100/H200); set it for other GPUs.
# - Build outputs go to target/cuda (CARGO_TARGET_DIR), apart from the CPU build; with --ci to
#   ~/.cache/pixl/cuda-target-ci, kept between runs on the same machine.
set -euo pipefail
ROOT="$(cd "$(dirname "$0")/.." && pwd)"
CUDA13="${PIXL_CUDA13:-${XDG_CACHE_HOME:-$HOME/.cache}/pixl/cuda13}"
MODE="${1:-release}"
case "$MODE" in
  release | --release) MODE=release ;;
  --ci | --env) ;;
  -h | --help) sed -n '2,8p' "$0"; exit 0 ;;
  *) echo "cuda-setup.sh: unknown argument $MODE (expected --ci, --env or nothing)" >&2; exit 2 ;;
esac

log() { echo "cuda-setup: $*" >&2; }

# ---- 1. CUDA 13.0 toolkit pieces from PyPI ----
if [ ! -x "$CUDA13/bin/nvcc" ]; then
  PY="$(command -v python3 || true)"
  [ -n "$PY" ] || { log "python3 with pip is needed to fetch the CUDA 13.0 wheels"; exit 1; }
  wheels="$(mktemp -d)"; unpacked="$(mktemp -d)"
  log "downloading the CUDA 13.0 toolkit wheels (about 100 MB) into $CUDA13"
  "$PY" -m pip download -q --no-deps -d "$wheels" \
    nvidia-cuda-nvcc==13.0.88 nvidia-cuda-crt==13.0.88 nvidia-nvvm==13.0.88 \
    nvidia-cuda-runtime==13.0.96 nvidia-cuda-cccl==13.0.85
  for w in "$wheels"/*.whl; do (cd "$unpacked" && "$PY" -m zipfile -e "$w" .); done
  rm -rf "$CUDA13"; mkdir -p "$(dirname "$CUDA13")"; cp -a "$unpacked/nvidia/cu13" "$CUDA13"
  ln -sfn lib "$CUDA13/lib64"
  chmod +x "$CUDA13"/bin/* "$CUDA13"/nvvm/bin/* 2>/dev/null || true
  rm -rf "$wheels" "$unpacked"
fi
# candle-kernels links -lcudart: offer only the static archive, so no libcudart.so is needed later.
mkdir -p "$CUDA13/linkstatic"
ln -sf ../lib/libcudart_static.a "$CUDA13/linkstatic/libcudart.a"

# ---- 2. candle-core with cudarc's dynamic loading ----
CANDLE_VERSION="$(awk '/^name = "candle-core"$/ { getline; gsub(/[^0-9.]/, ""); print; exit }' "$ROOT/Cargo.lock")"
PATCHED="$ROOT/target/cuda-patch/candle-core-$CANDLE_VERSION"
if [ ! -f "$PATCHED/.pixl-patched" ]; then
  (cd "$ROOT" && cargo fetch --locked -q)
  crate="$(ls "${CARGO_HOME:-$HOME/.cargo}"/registry/cache/*/"candle-core-$CANDLE_VERSION.crate" 2>/dev/null | head -1)"
  [ -n "$crate" ] || { log "candle-core $CANDLE_VERSION is not in cargo's registry cache"; exit 1; }
  rm -rf "$PATCHED"; mkdir -p "$(dirname "$PATCHED")"
  tar xzf "$crate" -C "$(dirname "$PATCHED")"
  sed -i 's/^    "dynamic-linking",$/    "dynamic-loading",/' "$PATCHED/Cargo.toml"
  grep -q '"dynamic-loading"' "$PATCHED/Cargo.toml" \
    || { log "could not switch candle-core $CANDLE_VERSION to cudarc dynamic-loading"; exit 1; }
  touch "$PATCHED/.pixl-patched"
fi

export PATH="$CUDA13/bin:$PATH" CUDA_PATH="$CUDA13" CUDA_HOME="$CUDA13"
export CUDA_COMPUTE_CAP="${CUDA_COMPUTE_CAP:-90}" CUDARC_CUDA_VERSION=13000
export RUSTFLAGS="${RUSTFLAGS:-} -L native=$CUDA13/linkstatic"
# CI keeps its cuda build outside the clone, so a later run on the same machine reuses the
# compiled dependencies (above all candle-kernels, whose nvcc step takes minutes).
if [ "$MODE" = --ci ]; then
  export CARGO_TARGET_DIR="${CARGO_TARGET_DIR:-${XDG_CACHE_HOME:-$HOME/.cache}/pixl/cuda-target-ci}"
else
  export CARGO_TARGET_DIR="${CARGO_TARGET_DIR:-$ROOT/target/cuda}"
fi
PATCH_ARG="patch.crates-io.candle-core.path=\"$PATCHED\""

if [ "$MODE" = --env ]; then
  printf 'export PATH=%q CUDA_PATH=%q CUDA_HOME=%q CUDA_COMPUTE_CAP=%q CUDARC_CUDA_VERSION=%q RUSTFLAGS=%q CARGO_TARGET_DIR=%q\n' \
    "$PATH" "$CUDA_PATH" "$CUDA_HOME" "$CUDA_COMPUTE_CAP" "$CUDARC_CUDA_VERSION" "$RUSTFLAGS" "$CARGO_TARGET_DIR"
  printf '# cargo commands then take: --config %q --features pixl-cli/cuda\n' "$PATCH_ARG"
  exit 0
fi

# ---- 3. build (and, for CI, test) ----
cd "$ROOT"
lock_backup="$(mktemp)"; cp Cargo.lock "$lock_backup"
trap 'cp "$lock_backup" "$ROOT/Cargo.lock"; rm -f "$lock_backup"' EXIT
cuda_cargo() { cargo "$1" --config "$PATCH_ARG" "${@:2}"; }

if [ "$MODE" = release ]; then
  cuda_cargo build --release -p pixl-cli --features cuda
  log "built $CARGO_TARGET_DIR/release/pixl with CUDA (kernels for compute capability $CUDA_COMPUTE_CAP)"
else
  # No debug info and no incremental caches: the debug build of every target is then a few GB
  # rather than about 20, and links faster.
  export CARGO_PROFILE_DEV_DEBUG="${CARGO_PROFILE_DEV_DEBUG:-0}" CARGO_INCREMENTAL="${CARGO_INCREMENTAL:-0}"
  start=$SECONDS
  cuda_cargo build --workspace --all-targets --features pixl-cli/cuda
  log "cuda build of every target: $((SECONDS - start)) s"
  # The CPU tests of the cuda build, all of them: the test binaries are built above (a subset of
  # packages would resolve other dependency features and compile again); among them the binary's
  # device handling (`pixl doctor`, --device cuda without a device).
  start=$SECONDS
  cuda_cargo test --workspace --features pixl-cli/cuda
  log "CPU tests of the cuda build: $((SECONDS - start)) s"
fi
