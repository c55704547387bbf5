"""Optics: Fourier MCAO PSF grid, NGS tip-tilt kernels, blur terms, seeing halo, distortion."""
