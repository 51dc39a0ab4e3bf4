"""refine --refine-intrinsics on synthetic scenes with a wrong camera file. Writes docs/intrinsics.md.

    python benchmarks/intrinsics.py [--seeds 0 1 2 3 4]
"""

from rgbd_gt.bench.intrinsics import main

if __name__ == "__main__":
    main()
