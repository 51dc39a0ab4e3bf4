"""Benchmarks: the paper's ICL-NUIM experiment (Sec. 4.1) and its baselines."""
