"""The PSF-star pool under an unresolved crowd's light, and the PSF-R correction grid.

On the 1e5-star frame the isolation test rated each neighbour by its box flux over the
frame's *global* sky, which there holds the unresolved crowd's light: faint neighbours
posed as bright and the pool emptied, so the correction kernels of the PSF-R model came
from stars far from their nodes (docs/measure-scale.md, twentieth pass). References
are independent of the code under test: the rendered truth (positions, fluxes, the
analytic PSF's widths) and brute-force distances.
"""

from __future__ import annotations

import json

import astropy.units as u
import numpy as np
import pytest
from astropy.table import QTable
from measure_helpers import Detector, SynthPSF, write_frames, write_prior

from mavispm.core.products import read_product
from mavispm.measure.stars.cli import run_stage
from mavispm.measure.stars.measure_frame import psfr_grid_for, read_frame
from mavispm.measure.stars.sky_mesh import mesh_sky

SHAPE = (360, 360)
PSF = SynthPSF(1.2, gradient=0.25)  # sigma 0.9-1.5 px in x: the kernel varies over the field
PRIOR_SIGMA = 0.7 * 7.36  # mas: narrower than the frame's PSF everywhere
CROWD = 400.0  # unresolved light at the left edge [electron / pixel] (sky 60)
SETTINGS = {"psf_stars_per_node": 20, "psfr_grid": 3}


def crowd_light(shape=SHAPE, peak=CROWD):
    """An unresolved crowd's light falling linearly from ``peak`` at x = 0 to 0 at the
    right edge [electron / pixel]."""
    ny, nx = shape
    return np.broadcast_to(peak * (1.0 - np.arange(nx) / (nx - 1)), shape)


def crowded_scene(path, seed=3, crowd=CROWD):
    """PSF-star candidates (V 17-19.5) on a jittered 24-px grid, each with a faint
    companion (V 25-26, 1.5-2.5 % of a V 21 star's flux: below the 1 % isolation ratio of
    every candidate) 6-10 px away, on a crowd's light of up to ``crowd`` e / px."""
    rng = np.random.default_rng(seed)
    g = np.arange(18, SHAPE[1] - 12, 24.0)
    bx, by = (a.ravel() + rng.uniform(-3, 3, a.size) for a in np.meshgrid(g, g))
    r, phi = rng.uniform(6, 10, len(bx)), rng.uniform(0, 2 * np.pi, len(bx))
    x, y = np.concatenate([bx, bx + r * np.cos(phi)]), np.concatenate([by, by + r * np.sin(phi)])
    mag = np.concatenate([rng.uniform(17.0, 19.5, len(bx)), rng.uniform(25.0, 26.0, len(bx))])
    light = crowd_light(peak=crowd) if crowd else None
    write_frames(path, SHAPE, x, y, mag, PSF, Detector(), seed=seed + 1, background=light)
    return path


@pytest.fixture(scope="module")
def crowded(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("pool")
    prior = tmp / "psfgrid.h5"
    write_prior(prior, PRIOR_SIGMA)
    return tmp, crowded_scene(tmp / "frames.h5"), prior


def test_mesh_sky_follows_the_crowd_light(crowded):
    """The mesh background against the rendered crowd light plus sky (truth)."""
    _, frames, _ = crowded
    frame = read_frame(frames)
    rng = np.random.default_rng(0)
    x, y = rng.uniform(20, 340, 200), rng.uniform(20, 340, 200)
    expected = frame.sky + CROWD * (1.0 - x / (SHAPE[1] - 1))
    got = mesh_sky(frame, x, y, 32)
    assert np.all(np.abs(got - expected) < 0.02 * CROWD)


def _kernel_errors(out):
    """Per PSF-R node: the fitted model's variance (the stretched prior's plus the
    kernel's) over the true PSF's, minus 1, along x (the axis of the strong variation)."""
    model = json.loads(read_product(out, "measured").attrs["psfr"])
    grid = model["grid"]
    kernels = np.array(model["kernels"]).reshape(grid, grid, 4)
    centres = (np.arange(grid) + 0.5) * SHAPE[0] / grid - 0.5
    err = np.empty((grid, grid))
    for j, yn in enumerate(centres):
        for i, xn in enumerate(centres):
            sx, _ = PSF.widths(xn, yn, SHAPE)
            cxx, _, _, stretch = kernels[j, i]
            err[j, i] = (cxx + (1.03 * stretch * PRIOR_SIGMA) ** 2) / (sx * 7.36) ** 2 - 1
    return err


def _flux_bias(out, frames):
    """Median fitted / true flux - 1 of the candidates (V < 20) in the left third of the
    frame (where the crowd's light is strongest), against the truth."""
    t = QTable.read(out, path="stars")
    truth = read_product(frames, "frames").tables["truth"]
    true_x = dict(zip(np.asarray(truth["id"]), np.asarray(truth["x_pix"], float)))
    xt = np.array([true_x[i] for i in np.asarray(t["id"])])
    s = ((t["flag"] & (1 | 2 | 16 | 32)) == 0) & (t["mag"].to_value(u.mag) < 20) & (xt < 120)
    assert s.sum() >= 50
    return float(np.median((t["flux"] / t["flux_true"]).to_value(u.one)[s])) - 1.0


def test_local_sky_rating_keeps_the_pool_and_the_kernels_local(crowded):
    """Rated over the local background the pool covers the frame: every node's kernel
    matches the true PSF's width, and the candidates' fluxes follow the truth. (Rated over
    the global sky, only candidates near the crowd-free right edge pass: the left nodes'
    kernels come from 1.4-px stars where the PSF is 0.9 px wide, the fluxes there 4 %
    high; the next test.)"""
    tmp, frames, prior = crowded
    out = run_stage(frames, {**SETTINGS, "psf_prior": str(prior)}, tmp / "m.h5", seed=0)
    attrs = read_product(out, "measured").attrs
    assert attrs["psf_model"] == "psfr"
    assert int(attrs["n_psf_stars"]) >= 150  # of 196 candidates (9 nodes x 20 nearest)
    err = _kernel_errors(out)
    assert np.all(np.abs(err) < 0.1), err
    assert abs(_flux_bias(out, frames)) < 0.025


def test_global_sky_rating_loses_the_left_of_the_field(crowded):
    """The same frame with ``psf_star_sky_mesh = 0`` and ``psfr_star_isolation = 12`` (the
    selection before 2026-12-03): the pool shrinks to the crowd-free strip and the left
    nodes' kernels are far too wide."""
    tmp, frames, prior = crowded
    cfg = {**SETTINGS, "psf_prior": str(prior), "psf_star_sky_mesh": 0, "psfr_star_isolation": 12}
    out = run_stage(frames, cfg, tmp / "g.h5", seed=0)
    assert int(read_product(out, "measured").attrs["n_psf_stars"]) < 40
    assert np.all(_kernel_errors(out)[:, 0] > 0.3)
    assert _flux_bias(out, frames) > 0.03


def test_psfr_grid_auto_follows_the_pool():
    """``psfr_grid = "auto"`` against brute-force distances: 5 x 5 when every node's
    ``ceil(per_node x 9 / 25)`` nearest pool stars lie within half a node spacing, else
    3 x 3 with ``per_node`` each."""
    rng = np.random.default_rng(5)
    shape = (1000, 1000)
    x, y = rng.uniform(0, 1000, 5000), rng.uniform(0, 1000, 5000)
    for n_pool, per_node in ((3000, 150), (300, 150), (3000, 1500)):
        pool = rng.choice(5000, n_pool, replace=False)
        grid, members, gx, gy = psfr_grid_for("auto", x, y, pool, shape, per_node)
        # brute force: the 5 x 5 nodes (cell centres) and each one's nearest stars
        c5 = (np.arange(5) + 0.5) * 200 - 0.5
        k5 = int(np.ceil(per_node * 9 / 25))
        reach = max(np.sort(np.hypot(x[pool] - xn, y[pool] - yn))[k5 - 1] for yn in c5 for xn in c5)
        expected = 5 if reach <= 100 else 3
        assert grid == expected, (n_pool, per_node, reach)
        assert len(members) == grid**2 and len(gx) == len(gy) == grid
        k = k5 if grid == 5 else per_node
        nodes = [(a, b) for b in gy for a in gx]
        for m, (xn, yn) in zip(members, nodes):
            d = np.hypot(x[pool] - xn, y[pool] - yn)
            assert len(m) == min(k, n_pool) and set(m) <= set(pool)
            assert np.hypot(x[m] - xn, y[m] - yn).max() <= np.sort(d)[k - 1] + 1e-9
    assert psfr_grid_for(4, x, y, pool, shape, 150)[0] == 4
