"""Shared helpers for the optics tests: small, fast settings."""

from __future__ import annotations

from mavispm.simulate.optics.model import validate_settings


def small_table(**psf) -> dict:
    """A ``[scene.optics]`` table with a coarse, fast PSF grid (3 x 3 nodes)."""
    base = {
        "n_nodes": 3,
        "pupil_sampling": 32,
        "psd_padding": 2.5,
        "stamp_size": "0.3 arcsec",
        "pixel_scale": "3.75 mas",
    }
    base.update(psf)
    return {"psf": base, "halo": {"size": "4 arcsec"}}


def small_settings(**psf):
    """:class:`OpticsSettings` for :func:`small_table`."""
    return validate_settings(small_table(**psf))
