"""The CUDA path against the CPU path (docs/gpu.md): prepare where open3d is, run on the GPU machine.

    python benchmarks/gpu.py prepare [--data ../shared/data] [--inputs bench_out/gpu]
    python benchmarks/gpu.py run [--inputs bench_out/gpu] [--devices cpu cuda] [--inits 3]
"""

from rgbd_gt.bench.gpu import main

if __name__ == "__main__":
    main()
