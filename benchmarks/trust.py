"""The verdict on a labelled set of right and wrong results (issue: trust). Writes docs/trust.md.

    python benchmarks/trust.py [--data ../shared/data] [--rejudge]
"""

from rgbd_gt.bench.trust import main

if __name__ == "__main__":
    main()
