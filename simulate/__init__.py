"""Simulation: cluster catalogues and epochs, optics (PSF grid, tip-tilt,
distortion), rendering and the detector."""
