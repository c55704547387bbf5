"""Dynamics: dispersion profiles, Jeans models, emcee fits and IMBH model
comparison."""
