"""Refine on the real PJLab LiDAR-camera scenes from random inits, per objective, and the joint
solve (issue: intensity-only scans). Writes docs/lidar.md.

    python benchmarks/lidar.py [--data ../shared/data] [--inits 10] [--rewrite] [--picks-only]
                               [--objectives nid 'nid + edges' ...]
"""

from rgbd_gt.bench.lidar import main

if __name__ == "__main__":
    main()
