#!/usr/bin/env bash
# Builds `pixl` with the `cuda` feature on a machine without a system CUDA toolkit.
#
# - nvcc, headers and the static CUDA runtime come from PyPI's CUDA **13.0** wheels, assembled
#   under $CUDA13 (default /opt/cuda13). 13.0 and not newer: a CUDA 13.0 (R580) driver JIT-compiles
#   PTX up to ISA 9.0 only, and newer nvcc emits newer PTX.
# - cudarc is built for CUDA 13.0 (CUDARC_CUDA_VERSION=13000) and loads libcuda / libcublas at run
#   time, so the binary runs on any machine whose driver and cuBLAS 13 libraries are installed
#   (put their directory on LD_LIBRARY_PATH).
# - Kernels are compiled for Hopper (CUDA_COMPUTE_CAP=90); override for other GPUs.
#
# Usage: scripts/cuda-setup.sh            # then: target/release/pixl relight --device cuda ...
# Status: written from the recipe in shared/cuda (measured there on an H100); the `cuda` build of
# this project has not been run in CI, which has no GPU.
set -euo pipefail
ROOT="$(cd "$(dirname "$0")/.." && pwd)"
CUDA13="${CUDA13:-/opt/cuda13}"

if [ ! -x "$CUDA13/bin/nvcc" ]; then
  wheels="$(mktemp -d)"; unpacked="$(mktemp -d)"
  python3 -m pip download --no-deps -d "$wheels" \
    nvidia-cuda-nvcc==13.0.88 nvidia-cuda-crt==13.0.88 nvidia-nvvm==13.0.88 \
    nvidia-cuda-runtime==13.0.96 nvidia-cuda-cccl==13.0.85
  for w in "$wheels"/*.whl; do (cd "$unpacked" && python3 -m zipfile -e "$w" .); done
  rm -rf "$CUDA13"; mkdir -p "$(dirname "$CUDA13")"; cp -a "$unpacked/nvidia/cu13" "$CUDA13"
  ln -sfn lib "$CUDA13/lib64"
  chmod +x "$CUDA13"/bin/* "$CUDA13"/nvvm/bin/* 2>/dev/null || true
  rm -rf "$wheels" "$unpacked"
fi
# candle-kernels links -lcudart: offer only the static archive, so no libcudart.so is needed later.
mkdir -p "$CUDA13/linkstatic"
ln -sf ../lib/libcudart_static.a "$CUDA13/linkstatic/libcudart.a"

cd "$ROOT"
PATH="$CUDA13/bin:$PATH" CUDA_PATH="$CUDA13" CUDA_HOME="$CUDA13" CUDA_COMPUTE_CAP="${CUDA_COMPUTE_CAP:-90}" \
CUDARC_CUDA_VERSION=13000 RUSTFLAGS="${RUSTFLAGS:-} -L native=$CUDA13/linkstatic" \
  cargo build --release -p pixl-cli --features cuda
echo "built target/release/pixl with CUDA"
