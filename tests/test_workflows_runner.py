"""Caching, selective re-runs and resumption of the workflow runner."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
from workflows_helpers import (
    ALL_NODES,
    TINY_WORKFLOW,
    fingerprints,
    read_log,
    run_in_subprocess,
    stand_in_registry,
    start_subprocess,
    write_workflow,
)

from mavispm.workflows.config import load_workflow
from mavispm.workflows.runner import WorkflowError, run_workflow


@pytest.fixture
def log(tmp_path, monkeypatch):
    path = tmp_path / "calls.log"
    monkeypatch.setenv("WF_TEST_LOG", str(path))
    return path


def _run(wf, workdir, **kw):
    kw.setdefault("scheduler", "serial")
    return run_workflow(wf, workdir=workdir, registry=stand_in_registry(), progress=False, **kw)


def test_second_run_does_no_stage_work_and_force_redoes_all(tmp_path, log):
    wf = write_workflow(tmp_path)
    first = _run(wf, tmp_path / "w", scheduler="threads")
    assert set(first.ran) == ALL_NODES
    assert len(read_log(log)) == len(ALL_NODES)
    before = fingerprints(first.rundir)
    second = _run(wf, tmp_path / "w", scheduler="threads")
    assert second.ran == []
    assert set(second.cached) == ALL_NODES
    assert len(read_log(log)) == len(ALL_NODES)  # no stage was called
    assert fingerprints(second.rundir) == before
    assert (second.rundir / "summary.json").is_file()
    forced = _run(wf, tmp_path / "w", force=True)  # --force: everything again, identically
    assert set(forced.ran) == ALL_NODES
    assert len(read_log(log)) == 2 * len(ALL_NODES)
    assert fingerprints(forced.rundir) == before


#: Successive one-setting edits and the nodes each must re-run (and only those).
EDITS = [
    ("per_bin = 30", "per_bin = 25", {"dynamics/main"}),
    (
        'noise = "0.1 mas"',
        'noise = "0.2 mas"',
        {"stars/main/e0", "stars/main/e1", "propermotions/main", "dynamics/main"},
    ),
    ('jitter = "0.05 mas"', 'jitter = "0.06 mas"', ALL_NODES - {"cluster", "optics/main"}),
    ('fwhm = "18 mas"', 'fwhm = "20 mas"', ALL_NODES - {"cluster"}),
    ("n_stars = 150", "n_stars = 140", ALL_NODES - {"optics/main"}),
    ("n_stars = 140", "n_stars = 150", set()),  # back to a cached state: nothing at all
]


def test_changing_one_setting_reruns_exactly_its_dependants(tmp_path, log):
    text = TINY_WORKFLOW
    wf = write_workflow(tmp_path, text)
    _run(wf, tmp_path / "w")
    for old, new, expected in EDITS:
        assert old in text
        text = text.replace(old, new)
        write_workflow(tmp_path, text)
        n_before = len(read_log(log))
        again = _run(wf, tmp_path / "w")
        assert set(again.ran) == expected, (old, new)
        assert len(read_log(log)) - n_before == len(expected)
    # the incrementally updated run equals a clean run of the final file
    clean = _run(wf, tmp_path / "clean")
    assert fingerprints(again.rundir) == fingerprints(clean.rundir)


def test_exception_in_a_stage_then_resume(tmp_path, log, monkeypatch):
    wf = write_workflow(tmp_path)
    monkeypatch.setenv("WF_TEST_FAIL", "propermotions")
    with pytest.raises(WorkflowError, match="propermotions/main.*injected failure"):
        _run(wf, tmp_path / "w")
    done_before = [line.split()[0] for line in read_log(log)]
    assert "dynamics" not in done_before  # the dependant never started
    monkeypatch.delenv("WF_TEST_FAIL")
    resumed = _run(wf, tmp_path / "w")
    assert set(resumed.ran) == {"propermotions/main", "dynamics/main"}
    clean = _run(wf, tmp_path / "clean")
    assert fingerprints(resumed.rundir) == fingerprints(clean.rundir)


def test_killed_process_resumes_to_identical_products(tmp_path, log):
    wf = write_workflow(tmp_path)
    code, err = run_in_subprocess(
        wf, tmp_path / "w", {"WF_TEST_KILL": "stars", "WF_TEST_LOG": str(log)}
    )
    assert code == -9, err
    killed_calls = [line.split()[0] for line in read_log(log)]
    assert killed_calls.count("stars") == 1 and "propermotions" not in killed_calls
    store = tmp_path / "w" / "store" / "stars"
    assert any(p.name.endswith(".partial") for p in store.iterdir())  # the half-done node
    n_before = len(read_log(log))
    resumed = _run(wf, tmp_path / "w")
    redone = {line.split()[0] for line in read_log(log)[n_before:]}
    assert redone == {"stars", "propermotions", "dynamics"}
    assert not any(n.startswith(("cluster", "optics", "frames")) for n in resumed.ran)
    clean = _run(wf, tmp_path / "clean")
    assert fingerprints(resumed.rundir) == fingerprints(clean.rundir)
    assert not any(p.name.endswith(".partial") for p in store.iterdir())


def test_two_concurrent_runs_share_the_work(tmp_path, log):
    wf = write_workflow(tmp_path)
    env = {"WF_TEST_LOG": str(log)}
    procs = [start_subprocess(wf, tmp_path / "w", env) for _ in range(2)]
    for proc in procs:
        _, err = proc.communicate(timeout=120)
        assert proc.returncode == 0, err
    calls = [line.split()[0] for line in read_log(log)]
    assert len(calls) == len(ALL_NODES)  # every node computed once in total
    clean = _run(wf, tmp_path / "clean")
    assert fingerprints(_run(wf, tmp_path / "w").rundir) == fingerprints(clean.rundir)


def test_studies_share_identical_nodes_and_random_streams(tmp_path, log):
    text = (
        TINY_WORKFLOW
        + "\n[studies.imbh.cluster]\nimbh_mass = 1500\n\n[studies.no_imbh.cluster]\nimbh_mass = 0\n"
    )
    wf = write_workflow(tmp_path, text)
    result = _run(wf, tmp_path / "w")
    stages = [line.split()[0] for line in read_log(log)]
    assert stages.count("optics") == 1  # same optics in both studies: one task
    assert stages.count("cluster") == 2
    summary = result.summary
    assert summary["stages"]["optics"] == {
        "tasks": 1,
        "ran": 1,
        "cached": 0,
        "failed": 0,
        "wall_s": pytest.approx(summary["stages"]["optics"]["wall_s"]),
    }
    seeds = {n["id"]: n["seed"] for n in summary["nodes"]}
    assert seeds["imbh/cluster"] == seeds["no_imbh/cluster"]
    assert seeds["imbh/frames/main/e1"] == seeds["no_imbh/frames/main/e1"]
    assert seeds["imbh/frames/main/e0"] != seeds["imbh/frames/main/e1"]
    # same star count and magnitudes, different dynamics: only the IMBH changes
    from mavispm.core.catalogue import read_catalogue

    a = read_catalogue(result.product("imbh/cluster")).epochs["e0"]
    b = read_catalogue(result.product("no_imbh/cluster")).epochs["e0"]
    assert len(a) == len(b) and (a["mag"] == b["mag"]).all()
    assert not (a["pm_x"] == b["pm_x"]).all()


def test_external_catalogue_source(tmp_path, log):
    wf = write_workflow(tmp_path)
    first = _run(wf, tmp_path / "w")
    cat = tmp_path / "external_catalogue.h5"
    shutil.copyfile(first.product("cluster"), cat)
    text = TINY_WORKFLOW.replace("[cluster]\nn_stars = 150\n", f'[catalogue]\npath = "{cat}"\n')
    ext = write_workflow(tmp_path, text, "ext.toml")
    wf_loaded = load_workflow(ext, stand_in_registry())
    assert [e.name for e in wf_loaded.variants[0].epochs] == ["e0", "e1"]
    second = _run(ext, tmp_path / "w")
    assert "cluster" not in {n["id"] for n in second.summary["nodes"]}
    assert set(second.ran) == ALL_NODES - {"cluster", "optics/main"}
    # the same catalogue content and seeds give the same products as the generated run
    fa, fb = fingerprints(first.rundir), fingerprints(second.rundir)
    shared = [k for k in fb if "frames" in k or "dynamics" in k]
    assert shared and all(fa[k] == fb[k] for k in shared)
    # a second run reuses everything; changing the file's content re-runs its users
    assert _run(ext, tmp_path / "w").ran == []


def test_fingerprint_ignores_only_time_stamps_and_timings(tmp_path):
    from mavispm.core.products import write_product
    from mavispm.workflows.cache import product_fingerprint

    def make(name, time_fit, value):
        return write_product(
            tmp_path / name,
            "measured",
            arrays={"a": np.array([1.0, value])},
            attrs={"time_fit": time_fit, "engine": "fast"},
        )

    reference = product_fingerprint(make("a.h5", 1.0, 2.0))
    assert product_fingerprint(make("b.h5", 9.5, 2.0)) == reference  # only the timing differs
    assert product_fingerprint(make("c.h5", 1.0, 2.0 + 1e-12)) != reference  # one bit of data


def test_dynamics_stage_draws_no_sampler_bars_unless_asked(monkeypatch, tmp_path):
    # the runner draws one bar per stage; the sampler's own bars would cut through them
    from mavispm.workflows import stages

    seen = []

    def spy(propermotions, settings, output, seed, **kw):
        seen.append(settings.get("progress"))
        return output

    monkeypatch.setattr(stages, "_stage", lambda name: spy)
    inputs = {"propermotions": tmp_path / "pm.h5"}
    stages.run_dynamics(inputs, {"walkers": 8}, {"plots": False}, 1, tmp_path)
    stages.run_dynamics(inputs, {"progress": True}, {"plots": False}, 1, tmp_path)
    assert seen == [False, True]
