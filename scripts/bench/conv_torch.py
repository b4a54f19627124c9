"""PyTorch's f32 3×3 convolutions on the shapes of `crates/pixl-nn/examples/bench_conv3x3.rs`.

Usage: python scripts/bench/conv_torch.py [THREADS]   (default: all cores)
Prints the median of 5 runs (after a warm-up) and GFLOP/s per shape, bias and ReLU included.
"""
import statistics
import sys
import time

import torch
import torch.nn.functional as F

SHAPES = [
    ("small output_conv2", 64, 32, 512, 1),
    ("small output_conv1", 128, 64, 256, 1),
    ("small refinenet1 rcu", 128, 128, 256, 1),
    ("paper refinenet1 rcu", 256, 256, 256, 1),
    ("paper resize3 s2", 1024, 1024, 32, 2),
    ("128 at 64x64", 128, 128, 64, 1),
    ("256 at 32x32", 256, 256, 32, 1),
    ("256 at 16x16", 256, 256, 16, 1),
    ("9 -> 32 at 256x256", 9, 32, 256, 1),
]


def main():
    if len(sys.argv) > 1:
        torch.set_num_threads(int(sys.argv[1]))
    print(f"torch {torch.__version__}, {torch.get_num_threads()} thread(s)")
    with torch.inference_mode():
        for name, cin, cout, side, stride in SHAPES:
            x = torch.randn(1, cin, side, side)
            w = torch.randn(cout, cin, 3, 3) * 0.05
            b = torch.full((cout,), 0.1)
            out = (side - 1) // stride + 1
            gflop = 2 * cin * 9 * cout * out * out / 1e9
            F.relu(F.conv2d(x, w, b, stride=stride, padding=1))
            times = []
            for _ in range(5):
                start = time.perf_counter()
                F.relu(F.conv2d(x, w, b, stride=stride, padding=1))
                times.append((time.perf_counter() - start) * 1e3)
            ms = statistics.median(times)
            print(f"{name:<22} torch     : {ms:8.1f} ms  {gflop / ms * 1e3:6.1f} GFLOP/s")


if __name__ == "__main__":
    main()
