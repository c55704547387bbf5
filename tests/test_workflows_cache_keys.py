"""Task keys hold only what changes results: UI and thread settings and plotting code
do not invalidate the cache, and products do not depend on them."""

from __future__ import annotations

import astropy.units as u
import numpy as np
import pytest
from dynamics_helpers import write_mock_propermotions
from render_helpers import epoch_table

from mavispm.core.catalogue import write_catalogue
from mavispm.dynamics import cli as dynamics_cli
from mavispm.workflows.cache import node_keys, product_fingerprint, without_keys
from mavispm.workflows.config import load_workflow
from mavispm.workflows.graph import expand
from mavispm.workflows.registry import PACKAGE_ROOT, code_files
from mavispm.workflows.stages import STAGE_MODULES, default_registry


def _keys(overrides=None):
    registry = default_registry()
    wf = load_workflow("quickstart", registry, overrides=overrides)
    return node_keys(expand(wf), registry)


def test_ui_settings_leave_every_key_unchanged_and_science_settings_do_not():
    base = _keys()
    ui = _keys({"dynamics.progress": True, "scene.render.threads": 1, "measure.progress": True})
    assert ui == base
    science = _keys({"dynamics.walkers": 14, "scene.render.gaussian_skew_limit": 0.2})
    changed = {nid.split("/")[0] for nid in base if science[nid] != base[nid]}
    assert changed == {"frames", "stars", "propermotions", "dynamics"}
    assert science["cluster"] == base["cluster"]


def test_without_keys_drops_nested_keys_only():
    settings = {"render": {"threads": 2, "halo": False}, "nexp": 3, "progress": True}
    out = without_keys(settings, ("render.threads", "progress", "absent.key"))
    assert out == {"render": {"halo": False}, "nexp": 3}
    assert settings["render"]["threads"] == 2  # the input is not modified


def test_plotting_code_is_in_no_product_key():
    plots = PACKAGE_ROOT / "simulate" / "optics" / "plots.py"
    report = PACKAGE_ROOT / "measure" / "propermotions" / "report.py"
    for stage, (_, patterns) in STAGE_MODULES.items():
        files = code_files(patterns)
        assert plots not in files and report not in files, stage
    cluster = code_files(STAGE_MODULES["cluster"][1])
    assert all("simulate/cluster" in str(p) for p in cluster) and len(cluster) > 5
    frames = code_files(STAGE_MODULES["frames"][1])
    assert PACKAGE_ROOT / "simulate" / "optics" / "tiptilt.py" in frames


def test_frames_do_not_depend_on_the_thread_count(tmp_path):
    """Rendering with 1 and 2 threads gives bitwise identical frames products (apart from
    the recorded settings)."""
    from optics_helpers import small_table

    from mavispm.simulate.render import cli as render_cli

    rng = np.random.default_rng(0)
    x, y = rng.uniform(-0.6, 0.6, (2, 40))
    cat = write_catalogue(tmp_path / "c.h5", {"e0": epoch_table(x, y, rng.uniform(17, 22, 40))})
    paths = []
    for threads in (1, 2):
        scene = {
            "nexp": 3,
            "detector": {"nx": 160, "ny": 160},
            "render": {"threads": threads},
            "optics": small_table(),
        }
        out = tmp_path / f"f{threads}.h5"
        paths.append(render_cli.run_stage(cat, "e0", scene, out, 5, cache_dir=tmp_path / "cache"))
    ignore = ("config", "scene")
    assert product_fingerprint(paths[0], ignore) == product_fingerprint(paths[1], ignore)


@pytest.mark.slow  # ~30 s on 2 busy cores, mostly numba compilation of the Jeans kernels
def test_dynamics_products_do_not_depend_on_progress_bars(tmp_path):
    pm = write_mock_propermotions(tmp_path / "pm.h5", seed=3, n_field=150)
    settings = {
        "walkers": 8,
        "max_steps": 60,
        "check_every": 30,
        "grid_size": 10,
        "projection_panels": 2,
        "projection_nodes": 3,
        "bin_size": 60,
        "n_bootstrap": 3,
        "evidence": False,
        "posterior": "emcee",
        "velocity_law": "free_kurtosis",  # one law: weighing two needs the evidences
    }
    outs = [
        dynamics_cli.run_stage(pm, {**settings, "progress": flag}, tmp_path / f"d{flag}.h5", 1)
        for flag in (False, True)
    ]
    ignore = ("config", "propermotions")
    assert product_fingerprint(outs[0], ignore) == product_fingerprint(outs[1], ignore)
    assert dynamics_cli.read_product(outs[0]).attrs["distance"] == 4.6 * u.kpc
