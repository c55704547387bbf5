"""Reliability and security findings of issue 18, one test (or more) per finding.

Each test fails on the code before the fix: it reproduces the reported attack or
failure and checks the promised behaviour (docs/workflows.md, "Reliability").
"""

from __future__ import annotations

import json
import os
import stat

import pytest
from workflows_helpers import TINY_WORKFLOW, stand_in_registry, write_workflow

from mavispm.core.errors import ConfigError, InputError
from mavispm.workflows.cli import main
from mavispm.workflows.config import load_workflow
from mavispm.workflows.runner import run_workflow


def _run(wf, workdir, **kw):
    kw.setdefault("scheduler", "serial")
    return run_workflow(wf, workdir=workdir, registry=stand_in_registry(), progress=False, **kw)


def _one_line_error(capsys, *names: str) -> str:
    err = capsys.readouterr().err.strip()
    assert err.startswith("mavispm: error:"), err
    assert "\n" not in err and "Traceback" not in err, err
    for name in names:
        assert name in err, (name, err)
    return err


@pytest.fixture
def stand_ins(tmp_path, monkeypatch):
    """The CLI runs the stand-in stages (logging to calls.log)."""
    from mavispm.workflows import stages

    monkeypatch.setenv("WF_TEST_LOG", str(tmp_path / "calls.log"))
    monkeypatch.setattr(stages, "default_registry", stand_in_registry)


def minimal_summary(**extra) -> dict:
    """The smallest summary.json that ``mavispm report`` accepts."""
    return {
        "workflow": "crafted",
        "nodes": [],
        "stages": {},
        "outputs": {"tables": []},
        **extra,
    }


def _crafted_rundir(tmp_path, summary) -> os.PathLike:
    rundir = tmp_path / "run"
    rundir.mkdir()
    (rundir / "summary.json").write_text(json.dumps(summary))
    return rundir


# ------------------------------------------------ 1. a run directory is data, never code


@pytest.mark.parametrize("form", ["mapping", "list"])
def test_report_never_imports_code_named_in_a_run_directory(tmp_path, capsys, monkeypatch, form):
    marker = tmp_path / "pwned"
    evil = tmp_path / "evil_module_rel18.py"
    evil.write_text(
        f"from pathlib import Path\nPath({str(marker)!r}).write_text('ran')\n"
        "def write_report(paths, outdir):\n    return []\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    ref = "evil_module_rel18:write_report"
    reports = {"stars": ref} if form == "mapping" else [ref]
    node = {
        "id": "stars/main/e0",
        "stage": "stars",
        "status": "ran",
        "products": {"main": "products/stars/main/e0/measured.h5"},
        "labels": {"scene": "main", "epoch": "e0"},
    }
    rundir = _crafted_rundir(tmp_path, minimal_summary(nodes=[node], stage_reports=reports))
    assert main(["report", str(rundir)]) == 2
    _one_line_error(capsys, "summary.json", "stage_reports" if form == "mapping" else ref)
    assert not marker.exists()
    assert not (rundir / "report.md").exists()


def test_report_accepts_registered_stage_names_and_old_run_directories(tmp_path):
    from mavispm.workflows.report import stage_report_functions, stage_report_names

    trusted = stage_report_functions()
    assert stage_report_names({"stage_reports": ["stars"]}) == ["stars"]
    # summary.json of earlier versions: the registered function of each stage is accepted
    assert stage_report_names({"stage_reports": {"stars": trusted["stars"]}}) == ["stars"]
    with pytest.raises(InputError, match="unknown stage report 'nope'"):
        stage_report_names({"stage_reports": ["nope"]})


@pytest.mark.parametrize(
    "bad",
    [
        [],
        {"workflow": "x"},
        {"workflow": "x", "nodes": [1], "stages": {}},
        {"workflow": "x", "nodes": [], "stages": {"cluster": {"tasks": "many"}}},
        minimal_summary(outputs={"tables": ["os.system"]}),
    ],
)
def test_malformed_summary_is_a_one_line_error(tmp_path, capsys, bad):
    rundir = _crafted_rundir(tmp_path, bad)
    assert main(["report", str(rundir)]) == 2
    _one_line_error(capsys, "summary.json")
    assert not (rundir / "report.md").exists()


def test_report_refuses_product_paths_and_labels_leading_outside(tmp_path, capsys):
    outside = {
        "id": "stars/x",
        "stage": "stars",
        "status": "ran",
        "products": {"main": "../../etc/passwd"},
        "labels": {},
    }
    rundir = _crafted_rundir(tmp_path, minimal_summary(nodes=[outside]))
    assert main(["report", str(rundir)]) == 2
    _one_line_error(capsys, "leads outside")
    (rundir / "summary.json").unlink()
    label = {**outside, "products": {"main": "products/m.h5"}, "labels": {"scene": "../../x"}}
    (rundir / "summary.json").write_text(json.dumps(minimal_summary(nodes=[label])))
    assert main(["report", str(rundir)]) == 2
    _one_line_error(capsys, "labels.scene")


# ------------------------------------------------ 2. no writes outside the work directory


@pytest.mark.parametrize(
    ("edit", "key"),
    [
        (('name = "tiny"', 'name = "../victim"'), "workflow.name"),
        (('name = "tiny"', 'name = "store"'), "workflow.name"),
        (('name = "tiny"', 'name = ".."'), "workflow.name"),
        (('name = "tiny"', 'name = "/tmp/abs"'), "workflow.name"),
        (("[scene]\n", '[scenes."../esc"]\n[scene]\n'), "scenes.../esc"),
        (("[cluster]\n", '[studies."a/../../b".cluster]\n[cluster]\n'), "studies.a/../../b"),
        (("times = [0, 5]", 'times = [0, 5]\nnames = ["e0", "../e1"]'), "epochs.names[1]"),
    ],
)
def test_names_that_would_escape_are_refused_before_any_work(tmp_path, edit, key):
    text = TINY_WORKFLOW.replace(*edit)
    assert text != TINY_WORKFLOW
    wf = write_workflow(tmp_path, text)
    with pytest.raises(ConfigError, match="key '" + key.replace(".", r"\.").replace("[", r"\[")):
        load_workflow(wf, stand_in_registry())


def test_workflow_name_cannot_delete_a_products_folder_outside(tmp_path, capsys, stand_ins):
    victim = tmp_path / "victim" / "products"
    victim.mkdir(parents=True)
    (victim / "precious.txt").write_text("keep")
    wf = write_workflow(tmp_path, TINY_WORKFLOW.replace('name = "tiny"', 'name = "../victim"'))
    assert main(["run", str(wf), "--workdir", str(tmp_path / "w"), "--quiet"]) == 2
    _one_line_error(capsys, "workflow.name", "../victim")
    assert (victim / "precious.txt").read_text() == "keep"
    assert not (tmp_path / "w").exists()


def test_unnamed_workflow_takes_a_safe_folder_name_from_its_file(tmp_path):
    wf = write_workflow(tmp_path, TINY_WORKFLOW.replace('name = "tiny"\n', ""), "my study.toml")
    assert load_workflow(wf, stand_in_registry()).name == "my_study"


# ------------------------------------------------ 3./4. emcee chains: keyed, resumed exactly


class _Interrupt(Exception):
    pass


def _gauss_space():
    from mavispm.dynamics.parameters import Parameter, ParameterSpace

    return ParameterSpace([Parameter("a", lo=-10, hi=10), Parameter("b", lo=-10, hi=10)])


def _gauss(mean: float, stop_after: int | None = None):
    calls = [0]

    def loglike(v):
        calls[0] += 1
        if stop_after is not None and calls[0] > stop_after:
            raise _Interrupt  # a kill in the middle of a block of steps
        return -0.5 * ((v[0] - mean) ** 2 + (v[1] / 2) ** 2)

    return loglike


_EMCEE = {"seed": 4, "walkers": 6, "max_steps": 600, "tau_factor": 10, "check_every": 40}


def _emcee(loglike, backend=None, key="k", **kw):
    from mavispm.dynamics.sampling import run_emcee

    return run_emcee(
        loglike,
        _gauss_space(),
        backend_path=backend,
        backend_key=key,
        progress=False,
        **{**_EMCEE, **kw},
    )


def _same_chain(a, b):
    import numpy as np

    np.testing.assert_array_equal(a.samples, b.samples)
    np.testing.assert_array_equal(a.tau, b.tau)
    assert (a.steps, a.converged) == (b.steps, b.converged)


def test_killed_emcee_fit_resumes_to_the_uninterrupted_result(tmp_path):
    import h5py

    clean = _emcee(_gauss(1.0))
    assert clean.converged and 80 < clean.steps < _EMCEE["max_steps"]
    backend = tmp_path / "fit.h5.emcee.h5"
    with pytest.raises(_Interrupt):
        _emcee(_gauss(1.0, stop_after=700), backend)
    with h5py.File(backend, "r") as f:
        stopped = int(f["mcmc"].attrs["iteration"])
    assert 0 < stopped < clean.steps and stopped % _EMCEE["check_every"] != 0  # mid-block
    resumed = _emcee(_gauss(1.0), backend)
    assert resumed.resumed_at == stopped
    _same_chain(resumed, clean)
    # a finished chain, run again: the same product, no step added, tau not NaN
    again = _emcee(_gauss(1.0), backend)
    assert again.resumed_at == clean.steps
    _same_chain(again, clean)


def test_emcee_backend_of_other_data_is_never_continued(tmp_path):
    backend = tmp_path / "fit.h5.emcee.h5"
    first = _emcee(_gauss(1.0), backend, key="data-A")
    other = _emcee(_gauss(3.0), backend, key="data-B")
    assert other.resumed_at == 0
    _same_chain(other, _emcee(_gauss(3.0), key="data-B"))
    assert abs(float(other.samples[:, 0].mean()) - 3.0) < 0.3
    assert abs(float(first.samples[:, 0].mean()) - 1.0) < 0.3
    # a damaged backend file (killed while writing its header) starts again
    backend.write_bytes(b"\x89HDF\r\n\x1a\n garbage")
    _same_chain(_emcee(_gauss(3.0), backend, key="data-B"), other)


def test_dynamics_backend_key_follows_the_data_and_settings():
    import numpy as np

    from mavispm.dynamics.cli import validate_settings
    from mavispm.dynamics.fit import backend_key
    from mavispm.dynamics.likelihood import StarSample

    rng = np.random.default_rng(0)
    cols = {c: rng.uniform(0.1, 1, 50) for c in ("R", "v_r", "v_t", "e_r", "e_t")}
    stars = StarSample(**cols, field_radius=2.0)
    s = validate_settings({})
    key = backend_key(stars, s, 4.7, True, 1)
    assert key == backend_key(StarSample(**cols, field_radius=2.0), s, 4.7, True, 1)
    moved = {**cols, "v_r": cols["v_r"].copy()}
    moved["v_r"][7] += 1e-9
    assert key != backend_key(StarSample(**moved, field_radius=2.0), s, 4.7, True, 1)
    assert key != backend_key(stars, validate_settings({"walkers": 40}), 4.7, True, 1)
    assert key != backend_key(stars, s, 4.7, True, 2)
    assert key != backend_key(stars, s, 4.7, False, 1)
    # the progress bar does not change the chain
    assert key == backend_key(stars, validate_settings({"progress": False}), 4.7, True, 1)


def test_a_task_whose_attempt_died_is_reported_in_the_run_record(tmp_path, monkeypatch):
    """A killed attempt (as a lost dask worker leaves it) shows in summary.json and the report."""
    from workflows_helpers import run_in_subprocess

    log = tmp_path / "calls.log"
    monkeypatch.setenv("WF_TEST_LOG", str(log))
    wf = write_workflow(tmp_path, TINY_WORKFLOW.replace("report = false", "report = true"))
    code, err = run_in_subprocess(wf, tmp_path / "w", {"WF_TEST_KILL": "stars"})
    assert code == -9, err
    resumed = _run(wf, tmp_path / "w")
    assert resumed.summary["interrupted_tasks"] == ["stars/main/e0"]
    node = next(n for n in resumed.summary["nodes"] if n["id"] == "stars/main/e0")
    assert node["interrupted_attempts"] == 1
    assert (
        "1 task(s) were redone after an attempt died" in (resumed.rundir / "report.md").read_text()
    )
    again = _run(wf, tmp_path / "w")  # all cached now: nothing to report
    assert again.summary["interrupted_tasks"] == []


# ------------------------------------------------ 9. run directories never alias the store writably


def test_cached_products_are_read_only_and_tampering_is_detected(tmp_path, monkeypatch):
    import h5py
    from workflows_helpers import fingerprints

    monkeypatch.setenv("WF_TEST_LOG", str(tmp_path / "calls.log"))
    wf = write_workflow(tmp_path)
    first = _run(wf, tmp_path / "w")
    clean = fingerprints(first.rundir)
    product = first.product("cluster")
    assert product.stat().st_mode & 0o222 == 0  # no write bit, run dir link and store alike
    if os.geteuid() != 0:
        with pytest.raises(PermissionError):
            open(product, "r+b")
    # a user allowed to write read-only files (root) edits the catalogue through the run dir
    os.chmod(product, 0o644)
    with h5py.File(product, "r+") as f:
        name = next(k for k in f if isinstance(f[k], h5py.Group))
        f[name].attrs["tampered"] = 1
    with pytest.warns(UserWarning, match="was changed after it was made"):
        second = _run(wf, tmp_path / "w")
    assert "cluster" in second.ran  # the edited product is not reused as cached
    assert fingerprints(second.rundir) == clean


@pytest.mark.parametrize("mask", [0o022, 0o002])
def test_products_and_run_files_respect_the_umask(tmp_path, monkeypatch, mask):
    from mavispm.core.atomic import atomic_path

    old = os.umask(mask)
    try:
        with atomic_path(tmp_path / "x.txt") as tmp:
            tmp.write_text("x")
        assert stat.S_IMODE((tmp_path / "x.txt").stat().st_mode) == 0o666 & ~mask
        monkeypatch.setenv("WF_TEST_LOG", str(tmp_path / "calls.log"))
        result = _run(write_workflow(tmp_path), tmp_path / "w")
    finally:
        os.umask(old)
    readable = 0o444 & ~mask
    assert stat.S_IMODE((result.rundir / "summary.json").stat().st_mode) == 0o666 & ~mask
    for path in (result.rundir / "products").rglob("*.h5"):  # read-only store files
        assert stat.S_IMODE(path.stat().st_mode) == readable, path


# ------------------------------------------------ 10. `mavispm cache`


def _aged(path, days: float, size: int):
    import time

    path.write_bytes(b"\0" * size)
    t = time.time() - days * 86400
    os.utime(path, (t, t))
    return path


def test_cache_command_shows_usage_and_cleans_by_age_then_size(tmp_path, capsys):
    cache = tmp_path / "cache"
    cache.mkdir()
    old = _aged(cache / "psfgrid-aaa.h5", 40, 3000)
    mid = _aged(cache / "halo-bbb.npz", 5, 2000)
    new = _aged(cache / "stampplan-ccc-m9.npz", 1, 1000)
    mine = _aged(cache / "notes.txt", 400, 10)  # not a cache file: never removed
    assert main(["cache", "--dir", str(cache)]) == 0
    assert "6.0 kB in 3 entries" in capsys.readouterr().out
    assert all(p.exists() for p in (old, mid, new, mine))  # showing removes nothing
    assert main(["cache", "--dir", str(cache), "--older-than", "30d", "--dry-run"]) == 0
    assert old.exists()
    assert main(["cache", "--dir", str(cache), "--older-than", "30d"]) == 0
    assert not old.exists() and mid.exists() and new.exists()
    assert main(["cache", "--dir", str(cache), "--max-size", "1.5kB"]) == 0
    assert not mid.exists() and new.exists() and mine.exists()  # least recently used first
    assert "freed 2.0 kB (1 entries); 1.0 kB left" in capsys.readouterr().out


@pytest.mark.parametrize(
    ("argv", "option"),
    [
        (["--max-size", "lots"], "--max-size"),
        (["--older-than=-3d"], "--older-than"),
        (["--workdir", "."], "--workdir"),
    ],
)
def test_cache_command_bad_options_are_one_line_errors(tmp_path, capsys, argv, option):
    assert main(["cache", "--dir", str(tmp_path), *argv]) == 2
    _one_line_error(capsys, option)


def test_cache_command_cleans_a_work_directory_store(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("WF_TEST_LOG", str(tmp_path / "calls.log"))
    wf = write_workflow(tmp_path)
    _run(wf, tmp_path / "w")
    argv = ["cache", "--dir", str(tmp_path / "none"), "--workdir", str(tmp_path / "w")]
    assert main(argv) == 0
    assert "product store" in capsys.readouterr().out
    assert main([*argv, "--max-size", "0"]) == 0
    assert not any((tmp_path / "w" / "store").glob("*/*"))
    again = _run(wf, tmp_path / "w")  # everything is simply recomputed
    assert len(again.ran) == len(again.summary["nodes"])


# ------------------------------------------------ 5. size limits at validation, before allocation


@pytest.mark.parametrize(
    ("table", "key"),
    [
        ("[scene.detector]\nnx = 1000000\nny = 1000000\n", "detector.nx"),
        ("[scene.optics.psf]\nn_nodes = 1000000\n", "n_nodes"),
        ("[scene.optics.psf]\npupil_sampling = 1000000\n", "pupil_sampling"),
    ],
)
def test_huge_scenes_are_refused_at_validation_with_the_memory_estimate(
    tmp_path, capsys, monkeypatch, table, key
):
    import tracemalloc

    monkeypatch.delenv("MAVISPM_MAX_MEMORY", raising=False)
    scene = tmp_path / "scene.toml"
    scene.write_text(table)
    out = tmp_path / "psf.h5"
    if key == "detector.nx":  # the detector is the frames stage's: check its validator
        import tomllib

        from mavispm.simulate.render.cli import validate_settings

        with pytest.raises(ConfigError, match=r"detector\.nx.*TiB.*MAVISPM_MAX_MEMORY"):
            validate_settings(tomllib.loads(table)["scene"])
        monkeypatch.setenv("MAVISPM_MAX_MEMORY", "inf")  # the explicit override
        assert validate_settings(tomllib.loads(table)["scene"]).detector.nx == 1000000
        return
    import mavispm.simulate.optics.fourier_psf  # noqa: F401 - imported before tracing
    from mavispm.workflows.cli import build_parser

    build_parser()
    tracemalloc.start()
    code = main(["simulate", "optics", "--scene", str(scene), "-o", str(out)])
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert code == 2
    _one_line_error(capsys, key, "iB of memory", "MAVISPM_MAX_MEMORY")
    assert peak < 200e6 and not out.exists()  # refused before any allocation


def test_huge_catalogue_is_refused_before_allocation_unless_allowed(tmp_path, capsys, monkeypatch):
    from mavispm.simulate.cluster.cli import validate_settings

    monkeypatch.delenv("MAVISPM_MAX_MEMORY", raising=False)
    out = tmp_path / "cat.h5"
    assert main(["simulate", "cluster", "--n-stars", "1000000000", "-o", str(out)]) == 2
    _one_line_error(capsys, "--n-stars", "GiB of memory")
    assert not out.exists()
    monkeypatch.setenv("MAVISPM_MAX_MEMORY", "10 TB")
    assert validate_settings({"n_stars": 1_000_000_000}).n_stars == 1_000_000_000
    monkeypatch.setenv("MAVISPM_MAX_MEMORY", "lots")
    with pytest.raises(ConfigError, match="MAVISPM_MAX_MEMORY"):
        validate_settings({"n_stars": 10})


# ------------------------------------------------ 6./8. extreme inputs and vague errors


@pytest.fixture(scope="module")
def small_catalogue(tmp_path_factory):
    from mavispm.simulate.cluster.cli import run_stage

    root = tmp_path_factory.mktemp("cat")
    return run_stage({"n_stars": 30, "epochs": [0.0]}, root / "catalogue.h5", seed=2)


def _edited_catalogue(src, dst, column, func):
    import numpy as np

    from mavispm.core.products import read_product, write_product

    prod = read_product(src)  # tables are compound datasets: edit them as tables
    hits = []
    for table in prod.tables.values():
        if column in table.colnames:
            col = table[column]
            unit = getattr(col, "unit", None)
            values = func(np.array(getattr(col, "value", col), dtype=float))
            table[column] = values if unit is None else values * unit
            hits.append(table)
    assert hits, column
    write_product(dst, prod.kind, tables=prod.tables, arrays=prod.arrays, attrs=prod.attrs)
    return dst


@pytest.mark.parametrize(
    ("column", "func", "words"),
    [
        ("mag", lambda m: m.__setitem__(0, -30.0) or m, ("mag", "electrons")),
        ("x", lambda x: x + 3600.0, ("stars falls on or near the", "detector")),
    ],
    ids=["V=-30", "outside"],
)
def test_catalogues_that_cannot_make_a_frame_are_refused(
    small_catalogue, tmp_path, capsys, column, func, words
):
    bad = _edited_catalogue(small_catalogue, tmp_path / "bad_cat.h5", column, func)
    out = tmp_path / "frames.h5"
    assert main(["simulate", "frames", str(bad), "--epoch", "e0", "-o", str(out)]) == 2
    _one_line_error(capsys, "bad_cat.h5", *words)
    assert not out.exists()


def test_imbh_heavier_than_its_cluster_is_refused_naming_the_flag(tmp_path, capsys):
    out = tmp_path / "c.h5"
    assert main(["simulate", "cluster", "--imbh-mass", "1e9", "-o", str(out)]) == 2
    err = _one_line_error(capsys, "--imbh-mass", "stellar mass")
    assert "key 'imbh_mass'" not in err and not out.exists()


def test_errors_name_the_flag_the_user_typed(tmp_path, capsys):
    star_list = tmp_path / "stars.csv"
    star_list.write_text("x,y,mag\n0,0,20\n")
    out = tmp_path / "c.h5"
    argv = ["simulate", "cluster", "--input", str(star_list), "--input-format", "mavisim"]
    assert main([*argv, "-o", str(out)]) == 2
    err = _one_line_error(capsys, "--pm-convention")
    assert "external.pm_convention" not in err


def test_typo_in_a_scene_file_is_refused_by_simulate_optics(tmp_path, capsys):
    scene = tmp_path / "scene.toml"
    scene.write_text("[opticz.psf]\nn_nodes = 3\n")
    out = tmp_path / "psf.h5"
    assert main(["simulate", "optics", "--scene", str(scene), "-o", str(out)]) == 2
    _one_line_error(capsys, "opticz", "did you mean 'optics'")
    assert not out.exists()


@pytest.mark.parametrize(
    ("edit", "words"),
    [
        ("nan", ("NaN",)),
        ("zero", ("constant",)),
        ("saturated", ("saturated",)),
        ("exptime", ("exptime",)),
    ],
)
def test_unmeasurable_frames_name_file_and_cause(tmp_path, edit, words):
    import numpy as np

    from mavispm.measure.stars.measure_frame import _check_usable_image

    rng = np.random.default_rng(0)
    image = rng.normal(100, 5, (40, 40))
    saturated = np.zeros(image.shape, bool)
    attrs = {"exptime": 30.0}
    if edit == "nan":
        image[:30] = np.nan
    elif edit == "zero":
        image[:] = 0.0
    elif edit == "saturated":
        saturated[:] = True
    else:
        attrs["exptime"] = -30.0
    _check_usable_image(rng.normal(100, 5, (40, 40)), np.zeros((40, 40), bool), {}, "ok.h5")
    with pytest.raises(InputError, match="frames.h5") as exc:
        _check_usable_image(image, saturated, attrs, tmp_path / "frames.h5")
    for word in words:
        assert word in str(exc.value)


def test_imbh_fit_from_two_stars_is_refused(tmp_path, capsys):
    import astropy.units as u
    import numpy as np
    from astropy.table import QTable

    from mavispm.core.products import write_product

    t = QTable()
    t["id"] = np.arange(2)
    # both inside the field radius min(max|x|, max|y|, max R) = 2 arcsec
    t["x"], t["y"], t["R"] = [3.0, -3.0] * u.arcsec, [3.0, -3.0] * u.arcsec, [1.0, 2.0] * u.arcsec
    for c in ("pm_r", "pm_t"):
        t[c] = [0.1, -0.2] * u.mas / u.yr
    for c in ("pm_r_err", "pm_t_err"):
        t[c] = [0.05, 0.05] * u.mas / u.yr
    pm = write_product(
        tmp_path / "two.h5", "propermotions", tables={"stars": t}, attrs={"distance": 4.6 * u.kpc}
    )
    out = tmp_path / "fit.h5"
    assert main(["dynamics", str(pm), "-o", str(out), "--fast"]) == 2
    _one_line_error(capsys, "two.h5", "only 2 usable stars")
    assert not out.exists()


def test_zero_proper_motion_errors_are_refused_unless_floored(tmp_path):
    import astropy.units as u
    import numpy as np
    from astropy.table import QTable

    from mavispm.core.products import write_product
    from mavispm.dynamics.cli import load_stars, validate_settings

    rng = np.random.default_rng(1)
    n = 30
    t = QTable()
    t["id"] = np.arange(n)
    x, y = rng.uniform(-10, 10, (2, n))
    t["x"], t["y"], t["R"] = x * u.arcsec, y * u.arcsec, np.hypot(x, y) * u.arcsec
    for c in ("pm_r", "pm_t"):
        t[c] = rng.normal(0, 0.3, n) * u.mas / u.yr
    t["pm_r_err"] = np.full(n, 0.05) * u.mas / u.yr
    t["pm_t_err"] = np.zeros(n) * u.mas / u.yr
    pm = write_product(
        tmp_path / "zero_err.h5",
        "propermotions",
        tables={"stars": t},
        attrs={"distance": 4.6 * u.kpc},
    )
    with pytest.raises(InputError, match=r"zero_err\.h5.*pm_t_err.*zero error"):
        load_stars(pm, validate_settings({}))
    stars, _ = load_stars(pm, validate_settings({"pm_error_floor": "0.02 mas/yr"}))
    assert np.all(stars.e_t == pytest.approx(0.02))


def test_two_stars_at_one_position_are_both_flagged_crowded():
    import numpy as np

    from mavispm.measure.stars.batched_fit import crowding_flags

    # the fit shared the light of a coincident pair 1.6 : 0.4; neither position is usable
    x = np.array([10.0, 10.2, 30.0])
    y = np.array([10.0, 10.1, 30.0])
    flux = np.array([1.6e4, 0.4e4, 1e4])
    flags = crowding_flags(x, y, flux, radius=3.0, ratio=5.0)
    assert flags.tolist() == [True, True, False]
    # resolved pairs keep the flux-ratio rule: only the faint one is crowded
    flags = crowding_flags(np.array([10.0, 12.5]), np.array([10.0, 10.0]), flux[:2], 3.0, 3.0)
    assert flags.tolist() == [False, True]


@pytest.mark.slow
def test_lost_dask_worker_is_retried_and_reported(tmp_path, monkeypatch):
    """A dask worker process killed mid-task: the scheduler retries, the run record says so."""
    distributed = pytest.importorskip("distributed")
    from workflows_helpers import fingerprints

    here = os.path.dirname(os.path.abspath(__file__))
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([here, os.environ.get("PYTHONPATH", "")]))
    monkeypatch.setenv("WF_TEST_KILL_ONCE", "stars")
    wf = write_workflow(tmp_path)
    with distributed.LocalCluster(
        n_workers=2,
        threads_per_worker=1,
        processes=True,
        protocol="tcp",
        host="127.0.0.1",
        dashboard_address=None,
    ) as cluster:
        result = _run(wf, tmp_path / "w", scheduler=cluster.scheduler_address)
    assert result.summary["interrupted_tasks"], result.summary["interrupted_tasks"]
    assert all(n.startswith("stars/") for n in result.summary["interrupted_tasks"])
    monkeypatch.delenv("WF_TEST_KILL_ONCE")
    clean = _run(wf, tmp_path / "clean")
    assert fingerprints(result.rundir) == fingerprints(clean.rundir)
