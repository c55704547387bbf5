"""Cluster catalogues and epochs: mass models, distribution functions, populations, external input."""
