"""Synthetic scanner-and-camera scenes with exact ground truth (`rgbd-gt synth`)."""
