"""Rendering: per-star stamps, seeing-halo convolution, sky, detector and stacked frames."""
