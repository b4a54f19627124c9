# Shared by scripts/bench-train-vs-pytorch.sh and scripts/check-train-grads.sh (sourced, not run,
# from the repository root): the Python with PyTorch, the `pixl` binary, peak-RSS measurement.
# The same conventions as scripts/bench-vs-pytorch.sh.
#
#   torch_python        sets PYTHON: $PYTHON if set (used as is), else the venv at
#                       $PIXL_TORCH_VENV (default $HOME/.cache/pixl/venv-torch), created on first
#                       use; installs torch, safetensors, numpy, openexr into it if missing
#                       (torch from $TORCH_INDEX_URL if set, else PyPI)
#   pixl_bin            sets PIXL_BIN: $PIXL_BIN if set, else runs
#                       `cargo build --release -p pixl-cli` and takes target/release/pixl
#                       (or $CARGO_TARGET_DIR/release/pixl)
#   with_rss FILE CMD…  runs CMD and writes its peak RSS in MB to FILE (getrusage of the waited-for
#                       children: the largest process's peak); returns CMD's status

torch_python() {
  if [ -z "${PYTHON:-}" ]; then
    local venv=${PIXL_TORCH_VENV:-$HOME/.cache/pixl/venv-torch}
    if [ ! -x "$venv/bin/python" ]; then
      echo "creating a venv at $venv" >&2
      mkdir -p "$(dirname "$venv")"
      python3 -m venv "$venv"
    fi
    PYTHON=$venv/bin/python
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
}

pixl_bin() {
  if [ -z "${PIXL_BIN:-}" ]; then
    cargo build --release -q -p pixl-cli
    PIXL_BIN=${CARGO_TARGET_DIR:-target}/release/pixl
  fi
  [ -x "$PIXL_BIN" ] || { echo "no pixl binary at $PIXL_BIN" >&2; return 1; }
}

with_rss() {
  local out=$1; shift
  "$PYTHON" -c '
import resource, subprocess, sys
rc = subprocess.run(sys.argv[2:]).returncode
with open(sys.argv[1], "w") as f:
    f.write("%.1f" % (resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024.0))
sys.exit(rc)' "$out" "$@"
}
