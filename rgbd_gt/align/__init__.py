"""The multimodal photometric aligner (Rotstein, Bracha, Kimmel, CVPR 2022) and its parts."""
