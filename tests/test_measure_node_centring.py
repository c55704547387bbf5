"""Node centring of a gridded ePSF on all stars (mavispm.measure.stars.node_centring)."""

import numpy as np
import pytest
from measure_helpers import SynthPSF, grid_positions, render_image, true_epsf

from mavispm.measure.stars.batched_fit import fit_stars
from mavispm.measure.stars.epsf_anchor import shift_epsf
from mavispm.measure.stars.node_centring import (
    NodeCentring,
    centring_from_summary,
    centring_summary,
    node_shifts,
    recentred_epsf,
    reference_list_id,
)
from mavispm.measure.stars.variable_psf import gridded_epsf


def test_node_shifts_undo_known_node_offsets_from_noisy_start_positions():
    """Every node of the exact ePSF moved by a known offset (up to 0.06 px); ~650
    stars start 0.05 px (rms) off their true positions. The fit with the moved ePSF
    puts each star off by minus the interpolated offset; the node shifts solved on
    all stars recover the offsets to the start errors' mean (0.05 / sqrt(~80 stars
    per node) ~ 0.006 px; the bilinear mixing couples the nodes, ~0.01 px rms), and the re-centred ePSF fits the stars at their true
    positions. Centred on a node's ~10 brightest stars only, as before, a node
    keeps an error of 0.05 / sqrt(10) ~ 0.016 px."""
    shape, psf = (800, 800), SynthPSF(1.3, gradient=0.1)
    rng = np.random.default_rng(3)
    x, y = grid_positions(shape, 30, 15, rng)
    flux = 10 ** rng.uniform(4.5, 5.5, len(x))
    image = render_image(shape, x, y, flux, psf, radius=12)
    sky = 50.0
    image = rng.poisson(image + sky).astype(float) - sky
    exact = true_epsf(psf, shape, grid=3, size=21)
    offsets = rng.uniform(-0.06, 0.06, (exact.n_basis, 2))
    moved = np.asarray(
        [shift_epsf(b, exact.oversampling, -ox, -oy) for b, (ox, oy) in zip(exact.basis, offsets)]
    )
    nodes = (np.asarray(exact.meta["nodes_x"]), np.asarray(exact.meta["nodes_y"]))
    off_psf = gridded_epsf(moved, *nodes, exact.oversampling)
    x0, y0 = x + rng.normal(0, 0.05, len(x)), y + rng.normal(0, 0.05, len(x))

    def fit(model):
        return fit_stars(image, model, x0, y0, read_noise_var=sky, sky0=0.0, return_model=False)

    first = fit(off_psf)
    ok = (first.flag & 32) == 0
    assert ok.sum() > 600
    # the moved ePSF moves every star by minus the interpolated offset
    assert np.sqrt(np.mean((first.x[ok] - x[ok]) ** 2)) > 0.025
    fisher = np.hypot(first.x_err, first.y_err) / np.sqrt(2)
    centring = node_shifts(off_psf, first.x, first.y, x0, y0, fisher, ok)
    miss = centring.shifts + offsets
    assert np.sqrt(np.mean(miss**2)) < 0.012 and np.max(np.abs(miss)) < 0.03, miss
    # the start scatter it estimated (no setting told it 0.05 px)
    assert 0.035 < centring.start_sigma < 0.065, centring.start_sigma
    second = fit(recentred_epsf(off_psf, centring))
    good = ok & ((second.flag & 32) == 0)
    resid = np.r_[second.x[good] - x[good], second.y[good] - y[good]]
    assert abs(np.mean(resid)) < 0.003 and np.sqrt(np.mean(resid**2)) < 0.012
    # the fitted positions moved by the interpolated shift (first order)
    shift = centring.at(off_psf, first.x, first.y)
    assert np.allclose(first.x[good] - shift[good, 0], second.x[good], atol=0.003)


def test_centring_error_passes_through_the_product_attribute():
    """A later epoch centred on an earlier ePSF adds that ePSF's centring error: the
    covariance written into the ``epsf_centring`` attribute gives back, at a node, the
    node's own variance, and midway between two nodes the bilinear mix
    ``sqrt(c_aa + c_bb + 2 c_ab) / 2`` (analytic)."""
    psf = true_epsf(SynthPSF(1.3), (300, 300), grid=3, size=11, oversampling=2)
    rng = np.random.default_rng(1)
    root = rng.normal(0, 1e-3, (9, 9))
    cov = root @ root.T  # a full, positive definite covariance [pixel^2]
    name = reference_list_id("truth", 0.0, np.arange(3), np.zeros(3), np.ones(3))
    back = centring_from_summary(
        centring_summary((NodeCentring(np.zeros((9, 2)), 0.01, 500, cov),), 7.36e-3, "start", name)
    )
    assert back.reference_id == name  # what a later epoch names as its registration
    # another list (one position moved by 1e-9 px), another name
    assert reference_list_id("truth", 0.0, np.arange(3), np.zeros(3), np.ones(3) + 1e-9) != name
    nx, ny = np.asarray(psf.meta["nodes_x"]), np.asarray(psf.meta["nodes_y"])
    gx, gy = np.meshgrid(nx, ny)  # row-major, as the nodes
    np.testing.assert_allclose(back.error_at(psf, gx.ravel(), gy.ravel()), np.sqrt(np.diag(cov)))
    mid = back.error_at(psf, np.array([(nx[0] + nx[1]) / 2]), np.array([ny[2]]))
    a, b = 6, 7  # nodes (0, 2) and (1, 2)
    assert mid[0] == pytest.approx(0.5 * np.sqrt(cov[a, a] + cov[b, b] + 2 * cov[a, b]))
    assert np.all(back.shifts == 0)  # the earlier ePSF is already centred
    # nodes centred on their PSF stars: nothing to inherit
    assert centring_from_summary(centring_summary(None, 7.36e-3)) is None
