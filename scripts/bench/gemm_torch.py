"""PyTorch's f32 matrix products on the shapes of `crates/pixl-nn/examples/bench_machine.rs`.

Usage: python scripts/bench/gemm_torch.py [THREADS]   (default: all cores)
Prints GFLOP/s per shape (best of 7), the same lines as the Rust example, for a side-by-side.
"""
import sys
import time

import torch

SHAPES = [
    ("paper qkv      ", 1032, 1024, 3072),
    ("paper mlp fc1  ", 1032, 1024, 4096),
    ("paper mlp fc2  ", 1032, 4096, 1024),
    ("paper proj     ", 1032, 1024, 1024),
    ("small mlp fc1  ", 1028, 384, 1536),
    ("small mlp fc2  ", 1028, 1536, 384),
    ("conv 3x3 64->32", 32, 576, 1024),
    ("conv 3x3 256   ", 256, 2304, 1024),
    ("conv 1x1 128   ", 128, 128, 65536),
    ("conv 1x1 32->6 ", 6, 32, 262144),
]


def main():
    if len(sys.argv) > 1:
        torch.set_num_threads(int(sys.argv[1]))
    t = torch.get_num_threads()
    print(f"torch {torch.__version__}, {t} thread(s), MKL {torch.backends.mkl.is_available()}, "
          f"mkldnn {torch.backends.mkldnn.is_available()}")
    with torch.inference_mode():
        for name, m, k, n in SHAPES:
            a = torch.rand(m, k)
            b = torch.rand(k, n)
            c = torch.empty(m, n)
            best = float("inf")
            for _ in range(7):
                start = time.perf_counter()
                torch.matmul(a, b, out=c)
                best = min(best, time.perf_counter() - start)
            print(f"gemm {name} M={m:<5} K={k:<5} N={n:<5} {t} thread(s): {2 * m * k * n / best / 1e9:7.1f} GFLOP/s")


if __name__ == "__main__":
    main()
