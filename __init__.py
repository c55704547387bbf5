"""mavispm: MAVIS multi-conjugate adaptive optics proper-motion pipeline.

Simulate MCAO images of star clusters as MAVIS (VLT) will take them, measure them,
turn epochs into proper motions and fit dynamical models to test for an
intermediate-mass black hole.

Sub-packages
------------
core      data formats (HDF5 products), units, errors, atomic writes
simulate  cluster catalogues and epochs, optics, rendering, detector
measure   ePSF building, forced PSF fitting, cross-matching, proper motions
dynamics  dispersion profiles, Jeans models, emcee fits, IMBH model comparison
workflows the runner, CLI and configuration
"""

__version__ = "0.1.0"
