"""Observer mode: a later epoch starts from the earlier epoch's measured positions.

The frames are synthesised independently (tests/measure_helpers.py) with a known
frame offset, rotation and per-star motions between the epochs; the truth is the
reference for scoring only. The key check: perturbing (or removing) the truth of
the later epoch does not change its measurement at all.
"""

from __future__ import annotations

import json

import astropy.units as u
import h5py
import numpy as np
import pytest
from measure_helpers import SynthPSF, write_frames

from mavispm.core.errors import InputError
from mavispm.core.products import read_product
from mavispm.measure.stars.cli import run_stage
from mavispm.measure.stars.start_list import histogram_offset

SHAPE = (200, 200)
FAST = {"psf_grid": 2, "psf_stars_per_node": 12, "psf_star_min_snr": 50.0, "epsf_iterations": 5}
OFFSET = (3.3, -2.1)  # pixel, frame 2 relative to frame 1
ROTATION = 2e-3  # rad
PSF = SynthPSF(1.2, gradient=0.2)


def _moved(x, y, rng):
    """Epoch-2 pixel positions: own motion (0.05 pix rms) plus the frame transform."""
    xm = x + rng.normal(0, 0.05, len(x))
    ym = y + rng.normal(0, 0.05, len(y))
    cx, cy = (SHAPE[1] - 1) / 2, (SHAPE[0] - 1) / 2
    c, s = np.cos(ROTATION), np.sin(ROTATION)
    x2 = cx + c * (xm - cx) - s * (ym - cy) + OFFSET[0]
    y2 = cy + s * (xm - cx) + c * (ym - cy) + OFFSET[1]
    return x2, y2


@pytest.fixture(scope="module")
def epochs(tmp_path_factory):
    rng = np.random.default_rng(3)
    n = 150
    x, y = rng.uniform(8, 192, n), rng.uniform(8, 192, n)
    mag = rng.uniform(16.0, 24.5, n)
    x2, y2 = _moved(x, y, rng)
    d = tmp_path_factory.mktemp("observer")
    f1, f2 = d / "e1.h5", d / "e2.h5"
    write_frames(f1, SHAPE, x, y, mag, PSF, seed=11, epoch=0.0)
    inside = (x2 > 1) & (x2 < 198) & (y2 > 1) & (y2 < 198)
    ids = np.arange(n)[inside]
    write_frames(f2, SHAPE, x2[inside], y2[inside], mag[inside], PSF, seed=12, epoch=10.0, ids=ids)
    m1 = run_stage(f1, FAST, d / "m1.h5", seed=0)
    m2 = run_stage(f2, FAST, d / "m2.h5", seed=0, earlier=[m1])
    return d, f1, f2, m1, m2


def _stars(path):
    return read_product(path, "measured").tables["stars"]


def test_later_epoch_starts_from_measured_positions(epochs):
    _, _, f2, m1, m2 = epochs
    prod = read_product(m2, "measured")
    assert prod.attrs["start"] == "measured"
    assert read_product(m1, "measured").attrs["start"] == "truth"  # epoch 1: the input list
    tr = json.loads(prod.attrs["start_transform"])["0"]
    # the injected frame offset (at the frame centre) and rotation, independent of the code
    cx, cy = (SHAPE[1] - 1) / 2, (SHAPE[0] - 1) / 2
    assert tr["a"][0] + tr["a"][1] * cx + tr["a"][2] * cy == pytest.approx(cx + OFFSET[0], abs=0.05)
    assert tr["b"][0] + tr["b"][1] * cx + tr["b"][2] * cy == pytest.approx(cy + OFFSET[1], abs=0.05)
    assert tr["a"][2] == pytest.approx(-np.sin(ROTATION), abs=5e-4)
    assert tr["b"][1] == pytest.approx(np.sin(ROTATION), abs=5e-4)
    # measured epoch-2 positions of bright stars agree with the epoch-2 truth
    stars = _stars(m2)
    good = (np.asarray(stars["flag"]) & (16 | 32)) == 0
    bright = good & (stars["mag"].to_value(u.mag) < 21)
    assert np.count_nonzero(bright) > 20
    dx = (stars["x"] - stars["x_true"]).to_value(u.mas)[bright]
    assert np.median(np.abs(dx)) < 1.0
    # ids come from epoch 1
    assert set(np.asarray(stars["id"])) <= set(np.asarray(_stars(m1)["id"]))


def _rewrite_truth(src, dst, dx_pix):
    """Copy a frames product with its truth positions moved by ``dx_pix`` (or removed)."""
    with h5py.File(src) as a, h5py.File(dst, "w") as b:
        for k, v in a.attrs.items():
            b.attrs[k] = v
        for name in a:
            if name == "truth" and dx_pix is None:
                continue
            a.copy(name, b)
        if dx_pix is not None:
            t = b["truth"]
            t["x_pix"][...] = t["x_pix"][...] + dx_pix
            t["y_pix"][...] = t["y_pix"][...] - dx_pix
            t["x"][...] = t["x"][...] + dx_pix * 7.36e-3


def test_no_truth_enters_a_later_epoch(epochs):
    d, _, f2, m1, m2 = epochs
    ref = _stars(m2)
    for label, shift in (("moved", 0.8), ("none", None)):
        frames = d / f"e2_{label}.h5"
        _rewrite_truth(f2, frames, shift)
        out = run_stage(frames, FAST, d / f"m2_{label}.h5", seed=0, earlier=[m1])
        stars = _stars(out)
        for col in ("id", "x_pix", "y_pix", "flux", "x_err", "flag"):
            if col == "flag":  # flag 16 (no truth match) is scoring; the rest is identical
                a, b = np.asarray(stars[col]) & ~16, np.asarray(ref[col]) & ~16
            else:
                a, b = np.asarray(stars[col]), np.asarray(ref[col])
            np.testing.assert_array_equal(a, b, err_msg=f"{label}: {col}")
    # the truth-forced option does use the (perturbed) truth
    forced = run_stage(
        d / "e2_moved.h5", {**FAST, "later_epochs": "truth"}, d / "m2_t.h5", seed=0, earlier=[m1]
    )
    assert read_product(forced, "measured").attrs["start"] == "truth"
    assert not np.array_equal(np.asarray(_stars(forced)["x_pix"])[:5], ref["x_pix"][:5])


def test_histogram_offset_recovers_shift():
    rng = np.random.default_rng(0)
    x, y = rng.uniform(0, 500, 200), rng.uniform(0, 500, 200)
    clutter = rng.uniform(0, 500, (2, 300))
    xn = np.concatenate([x[:150] + 7.4, clutter[0]])
    yn = np.concatenate([y[:150] - 12.6, clutter[1]])
    dx, dy, votes = histogram_offset(x, y, xn, yn, search=20.0)
    assert dx == pytest.approx(7.4, abs=1e-9) and dy == pytest.approx(-12.6, abs=1e-9)
    assert votes >= 150


def test_offset_beyond_search_is_refused(epochs, tmp_path):
    d, f1, _, m1, _ = epochs
    rng = np.random.default_rng(3)
    n = 150
    x, y = rng.uniform(8, 192, n), rng.uniform(8, 192, n)
    mag = rng.uniform(16.0, 24.5, n)
    far = tmp_path / "far.h5"
    keep = x + 60 < 198
    write_frames(far, SHAPE, x[keep] + 60, y[keep], mag[keep], PSF, seed=1, epoch=5.0)
    with pytest.raises(InputError, match="offset"):
        run_stage(far, FAST, tmp_path / "m.h5", seed=0, earlier=[m1])
    assert not (tmp_path / "m.h5").exists()


def test_workflow_graph_chains_later_epochs():
    """Observer mode is the default of the shipped workflows: each later epoch's stars
    node takes the earlier epochs' stars nodes as its ``earlier`` input;
    ``later_epochs = "truth"`` restores independent epochs."""
    from mavispm.workflows.config import load_workflow
    from mavispm.workflows.graph import expand

    overrides = {"epochs.times": [0, 5, 10]}
    nodes = expand(load_workflow("quickstart", overrides=overrides))
    stars = sorted(n for n in nodes if nodes[n].stage == "stars")
    assert len(stars) == 3
    assert "earlier" not in nodes[stars[0]].inputs
    assert nodes[stars[1]].inputs["earlier"] == [stars[0]]
    assert nodes[stars[2]].inputs["earlier"] == stars[:2]
    overrides["measure.later_epochs"] = "truth"
    nodes = expand(load_workflow("quickstart", overrides=overrides))
    assert not any("earlier" in n.inputs for n in nodes.values())
