"""The mesh background of the PSF stars' isolation test (``mesh_sky``, ``sky_mesh``).

The reference is independent of the code under test: a frame whose background is known
analytically (a tilted plane plus a broad bump, with Poisson stars on it, read noise and
a masked patch of garbage pixels), and photutils' ``Background2D`` (the library whose
algorithm ours repeats; kept as our own for its cost, docs/measure-scale.md).
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from measure_helpers import SynthPSF, render_image
from photutils.background import Background2D, MedianBackground

from mavispm.core.frame import Frame
from mavispm.measure.stars.sky_mesh import mesh_sky, sky_mesh

SHAPE = (400, 464)  # 12.5 x 14.5 blocks of 32: narrower edge blocks on two sides
MESH = 32
SKY = 60.0  # the frame's global sky [electron / pixel]: below the background everywhere
RN2 = 36.0  # read-noise variance [electron^2]
PATCH = (slice(186, 292), slice(58, 166))  # masked: covers 3 x 3 blocks entirely
#: Tolerances on (estimate - truth) / local pixel noise. A block median of 1,024 pixels
#: scatters by 1.25 / 32 = 0.04 of it (a narrower edge block by up to 0.055, extrapolated
#: to the frame's edge x 1.5), and the stars (~2 % of the pixels above 1 sigma) raise it
#: by ~0.02: the median over the frame, the rms, the worst of 4,000 positions, and the
#: worst where the bilinear interpolation reaches the masked patch's blocks (no data
#: there: the inverse-distance mean of the blocks around).
MEDIAN_TOL, RMS_TOL, MAX_TOL, PATCH_TOL = 0.04, 0.1, 0.4, 0.6


def near_patch(x, y):
    """Positions whose interpolation involves a block of the masked patch."""
    (ys, xs) = PATCH
    return (
        (y > ys.start - MESH) & (y < ys.stop + MESH) & (x > xs.start - MESH) & (x < xs.stop + MESH)
    )


def check(err, x, y):
    """The tolerances, or the failed one's name and value."""
    near = near_patch(x, y)
    away = err[~near]
    figures = {
        "median": (abs(np.median(err)), MEDIAN_TOL),
        "rms": (np.sqrt(np.mean(away**2)), RMS_TOL),
        "max": (np.abs(away).max(), MAX_TOL),
        "patch max": (np.abs(err[near]).max(), PATCH_TOL),
    }
    return {k: round(float(v), 3) for k, (v, tol) in figures.items() if not v < tol}


def true_background(x, y):
    """The analytic background [electron / pixel]: a plane steeper in y than in x (the
    3 x 3 median of a replicated edge is then off by a block's step) plus a broad bump."""
    bump = 60.0 * np.exp(-((x - 250.0) ** 2 + (y - 180.0) ** 2) / (2 * 220.0**2))
    return 150.0 + 0.35 * x + 0.5 * y + bump


@pytest.fixture(scope="module")
def scene():
    """The frame and 4,000 positions over all of it (edges and the masked patch too)."""
    rng = np.random.default_rng(11)
    ny, nx = SHAPE
    yy, xx = np.mgrid[0:ny, 0:nx]
    n = 150
    sx, sy = rng.uniform(-5, nx + 5, n), rng.uniform(-5, ny + 5, n)
    flux = 10 ** rng.uniform(3, 5, n)
    stars = render_image(SHAPE, sx, sy, flux, SynthPSF(1.2))
    image = rng.poisson(true_background(xx, yy) + stars) + rng.normal(0, np.sqrt(RN2), SHAPE)
    bad = np.zeros(SHAPE, bool)
    bad[PATCH] = True
    image[PATCH] = 5e4  # garbage under the mask
    frame = Frame(image, np.zeros(SHAPE, bool), SKY, RN2, 0.00736, bad=bad)
    x, y = rng.uniform(-0.5, nx - 0.5, 4000), rng.uniform(-0.5, ny - 0.5, 4000)
    return frame, x, y


def normalised_errors(values, x, y):
    """(estimate - truth) / the local pixel noise (Poisson on the truth plus read noise)."""
    truth = true_background(x, y)
    return (values - truth) / np.sqrt(truth + RN2)


def library(frame, filter_size=3):
    """photutils' ``Background2D`` with the mesh's settings (block medians, no clipping,
    every block with a usable pixel, the bad pixels masked)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return Background2D(
            frame.image.astype(np.float32),
            MESH,
            mask=frame.bad,
            filter_size=filter_size,
            exclude_percentile=100.0,
            sigma_clip=None,
            bkg_estimator=MedianBackground(),
        )


def test_mesh_sky_finds_the_analytic_background(scene):
    """Everywhere, up to the corners, the narrower edge blocks and inside the masked
    patch: within a few per cent of the pixel noise of the analytic truth."""
    frame, x, y = scene
    err = normalised_errors(mesh_sky(frame, x, y, MESH), x, y)
    assert check(err, x, y) == {}


def test_background2d_finds_the_analytic_background_inside(scene):
    """The library path on the same frame, its full-resolution background at the pixels:
    within the same tolerance at least two blocks from the edges (at the edges its NaN
    padding of the 3 x 3 median sets a block half a block's step of a perpendicular
    gradient towards the inside)."""
    frame, x, y = scene
    ny, nx = SHAPE
    inside = (x > 2 * MESH) & (x < nx - 2 * MESH) & (y > 2 * MESH) & (y < ny - 2 * MESH)
    xi, yi = x[inside], y[inside]
    bkg = library(frame).background[np.rint(yi).astype(int), np.rint(xi).astype(int)]
    err = normalised_errors(bkg, np.rint(xi), np.rint(yi))
    assert check(err, np.rint(xi), np.rint(yi)) == {}


def test_block_medians_and_mesh_are_background2d(scene):
    """Cross-check with the library: the block medians (narrower edge blocks and partly
    masked ones included) are ``Background2D``'s without the filter to float32 rounding,
    a block without usable pixels is NaN where the library counts none, and the smoothed
    mesh (those blocks filled as the library does) is its ``background_mesh`` (3 x 3
    median) off the edge blocks, which the two pad differently by design."""
    frame, _, _ = scene
    ours = sky_mesh(frame, MESH)
    raw = library(frame, filter_size=1)
    empty = raw.n_pixels_mesh == 0
    assert empty.sum() == 9
    np.testing.assert_array_equal(np.isnan(ours.medians), empty)
    np.testing.assert_allclose(ours.medians[~empty], raw.background_mesh[~empty], atol=1e-3)
    smooth = library(frame).background_mesh
    clear = np.ones(empty.shape, bool)
    clear[[0, -1], :] = clear[:, [0, -1]] = False
    np.testing.assert_allclose(ours.background[clear], smooth[clear], atol=1e-3)


@pytest.mark.parametrize("broken", ["half-block shift", "mask ignored", "block means"])
def test_a_broken_mesh_fails_the_truth_check(scene, broken):
    """The check above can fail: a mesh off by half a block, one that takes the masked
    garbage, or one of block means (the stars in them) is out of tolerance."""
    frame, x, y = scene
    if broken == "half-block shift":
        values = mesh_sky(frame, x + MESH / 2, y + MESH / 2, MESH)
    elif broken == "mask ignored":
        blind = Frame(frame.image, frame.saturated, SKY, RN2, 0.00736, bad=np.zeros(SHAPE, bool))
        values = mesh_sky(blind, x, y, MESH)
    else:
        image = np.where(frame.bad, np.nan, frame.image)
        ny, nx = SHAPE
        with warnings.catch_warnings():  # the masked patch's blocks: NaN
            warnings.simplefilter("ignore", RuntimeWarning)
            means = np.array(
                [
                    [np.nanmean(image[j : j + MESH, i : i + MESH]) for i in range(0, nx, MESH)]
                    for j in range(0, ny, MESH)
                ]
            )
        fake = Frame(np.repeat(np.repeat(means, MESH, 0), MESH, 1)[:ny, :nx], frame.saturated,
                     SKY, RN2, 0.00736, bad=frame.bad)  # fmt: skip
        values = mesh_sky(fake, x, y, MESH)
    failed = check(normalised_errors(values, x, y), x, y)
    assert failed
