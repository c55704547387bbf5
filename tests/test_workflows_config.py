"""Workflow files are validated whole, with clear errors, before any work starts."""

from __future__ import annotations

import pytest
from workflows_helpers import TINY_WORKFLOW, read_log, stand_in_registry, write_workflow

from mavispm.core.errors import ConfigError
from mavispm.workflows.config import load_workflow, resolve_workflow_path
from mavispm.workflows.graph import derive_seed, expand
from mavispm.workflows.runner import run_workflow


def _replace(old, new):
    assert old in TINY_WORKFLOW
    return TINY_WORKFLOW.replace(old, new)


BAD_FILES = [
    # (workflow text, expected key in the message, expected words)
    (TINY_WORKFLOW + "\n[extra]\na = 1\n", "key 'extra'", "unknown key"),
    (_replace("[measure]", "[measure]\nnosie = 1"), "key 'nosie'", "did you mean 'noise'"),
    (_replace("seed = 7", 'seed = "seven"'), "key 'workflow.seed'", "expected an integer"),
    (_replace('noise = "0.1 mas"', 'noise = "0.1 kg"'), "key 'noise'", "expected a number in mas"),
    (_replace("per_bin = 30", "per_bin = 2.5"), "key 'per_bin'", "expected an integer"),
    (_replace("times = [0, 5]", "times = [0]"), "key 'epochs.times'", "at least 2 epochs"),
    (_replace("times = [0, 5]", 'times = [0, "5 kg"]'), "key 'epochs.times[1]'", "time in years"),
    (_replace("times = [0, 5]", "times = [5, 5]"), "key 'epochs.times'", "duplicate"),
    (_replace("[propermotions]\n", ""), "key 'dynamics'", "needs proper motions"),
    (_replace('[measure]\nnoise = "0.1 mas"\n', ""), "key 'propermotions'", "needs measured stars"),
    (TINY_WORKFLOW + '\n[catalogue]\npath = "x.h5"\n', "key 'catalogue'", "not both"),
    (
        _replace("[cluster]\nn_stars = 150\n", '[catalogue]\npath = "missing.h5"\n'),
        "key 'catalogue.path'",
        "does not exist",
    ),
    (_replace("[cluster]\nn_stars = 150\n", ""), "key 'cluster'", "no cluster source"),
    (_replace("fits = false", "fits = 1"), "key 'outputs.fits'", "true or false"),
    (
        _replace("fits = false", 'tables = ["nope"]'),
        "key 'outputs.tables[0]'",
        "unknown report table",
    ),
    (
        TINY_WORKFLOW + '\n[[sweep]]\nparameter = "dynamics.per_bin"\nvalues = []\n',
        "key 'sweep[0].values'",
        "non-empty",
    ),
    (
        TINY_WORKFLOW + '\n[[sweep]]\nparameter = "nothing.x"\nvalues = [1]\n',
        "key 'sweep[0].parameter'",
        "first part",
    ),
    (
        TINY_WORKFLOW + '\n[[sweep]]\nparameter = "dynamics.per_bin"\nvalues = [10, "x"]\n',
        "key 'per_bin'",
        "sweep point per_bin=x",
    ),
    (TINY_WORKFLOW + "\n[studies.a.cluster]\nn_stars = -1.5\n", "key 'n_stars'", "study 'a'"),
    (
        TINY_WORKFLOW + "\n[studies.a.workflow]\nseed = 1\n",
        "key 'studies.a.workflow'",
        "unknown key",
    ),
    (TINY_WORKFLOW + "\n[scenes.I.render]\nx = 1\n", "key 'render'", "table [scenes.I]"),
    (
        _replace("n_stars = 150", "n_stars = 150\nepochs = [0, 1]"),
        "key 'cluster.epochs'",
        "[epochs] table",
    ),
    ("[workflow\nname = 1\n", "file", "invalid TOML"),
]


@pytest.mark.parametrize(("text", "key", "words"), BAD_FILES)
def test_invalid_workflow_files_fail_before_any_work(tmp_path, monkeypatch, text, key, words):
    log = tmp_path / "calls.log"
    monkeypatch.setenv("WF_TEST_LOG", str(log))
    wf = write_workflow(tmp_path, text)
    with pytest.raises(ConfigError) as err:
        run_workflow(wf, workdir=tmp_path / "w", registry=stand_in_registry(), progress=False)
    msg = str(err.value)
    assert str(wf) in msg  # names the file
    assert key in msg
    assert words in msg
    assert read_log(log) == []  # no stage ran
    assert not (tmp_path / "w").exists()  # nothing was written


def test_cli_reports_config_errors_in_one_line(tmp_path, capsys):
    from mavispm.workflows.cli import main

    wf = write_workflow(tmp_path, TINY_WORKFLOW + "\n[extra]\n")
    code = main(["run", str(wf), "--workdir", str(tmp_path / "w")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert len(err) == 1 and "unknown key" in err[0] and str(wf) in err[0]


def test_missing_workflow_file_lists_shipped_ones(tmp_path):
    with pytest.raises(ConfigError, match="workflow file not found"):
        resolve_workflow_path(tmp_path / "nope.toml")


def test_scene_overlays_studies_and_sweeps_expand(tmp_path):
    text = (
        TINY_WORKFLOW
        + '\n[scenes.I]\n[scenes.III.optics]\nfwhm = "22 mas"\n[scenes.III.measure]\nnoise = "0.3 mas"\n'
        + "\n[studies.imbh.cluster]\nimbh_mass = 1500\n[studies.none.cluster]\nimbh_mass = 0\n"
        + '\n[[sweep]]\nparameter = "dynamics.per_bin"\nvalues = [20, 30]\n'
    )
    wf = load_workflow(write_workflow(tmp_path, text), stand_in_registry())
    assert len(wf.variants) == 4
    v = wf.variants[0]
    assert v.study == "imbh" and v.point.label == "per_bin=20"
    scenes = {s.name: s for s in v.scenes}
    assert scenes["I"].optics == {"fwhm": "18 mas"}
    assert scenes["III"].optics == {"fwhm": "22 mas"}
    assert scenes["III"].measure == {"noise": "0.3 mas"}
    assert v.cluster["imbh_mass"] == 1500 and v.dynamics["per_bin"] == 20
    nodes = expand(wf)
    assert "imbh/per_bin=20/frames/III/e1" in nodes
    assert nodes["imbh/per_bin=30/dynamics/I"].settings["per_bin"] == 30
    # each fit sees the IMBH and no-IMBH truth catalogues of its own sweep point
    dyn = nodes["none/per_bin=30/dynamics/III"]
    assert dyn.inputs["truth"] == "imbh/per_bin=30/cluster"
    assert dyn.inputs["truth_no_imbh"] == "none/per_bin=30/cluster"
    assert nodes["imbh/per_bin=20/propermotions/I"].inputs["truth"] == "imbh/per_bin=20/cluster"
    order = list(nodes)
    assert all(order.index(u) < order.index(n) for n in nodes for u in nodes[n].upstream())
    # 2 studies x 2 points x (cluster + 2 scenes x (optics + 2 x (frames + stars) + pm + dyn))
    assert len(nodes) == 4 * (1 + 2 * (1 + 4 + 2))


def test_seeds_depend_on_stage_scene_and_epoch_only():
    assert derive_seed(1, "frames", "I", "e0") == derive_seed(1, "frames", "I", "e0")
    seeds = {
        derive_seed(s, "frames", sc, e) for s in (1, 2) for sc in ("I", "II") for e in ("e0", "e1")
    }
    assert len(seeds) == 8
    assert all(0 <= s < 2**31 for s in seeds)
