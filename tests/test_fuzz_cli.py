"""Fuzzing every ``mavispm`` entry point and product reader with hostile inputs.

Every command gets, in each of its file inputs, a missing file, an empty file,
a folder, a text file, binary junk, an HDF5 product cut in half, a product of
the wrong kind and a product with NaN/inf values; options get values of the
wrong kind or sign; outputs point at folders and at files below files. The
promises (docs/workflows.md, "Reliability"):

* a one-line error (``mavispm...: error: ...``, no traceback) that names the
  file or the option;
* exit status 2;
* no output file created, and an existing output left byte for byte as it was.

The fast part runs in CI (inputs made once per module, commands called in
process); ``-m slow`` adds hostile frames and measured products, which need a
rendered frame.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest

from mavispm.core.errors import MavispmError
from mavispm.core.products import read_product
from mavispm.workflows.cli import main

HOSTILE = ("missing", "empty", "folder", "text", "binary", "truncated", "wrong_kind", "nan")

#: Product kinds read by the entry points (and the kind of a catalogue, to be "wrong").
KINDS = ("catalogue", "psfgrid", "frames", "measured", "propermotions", "dynamics")


@pytest.fixture(scope="module")
def inputs(tmp_path_factory) -> Path:
    """A folder with one valid catalogue and every hostile input made from it."""
    from mavispm.simulate.cluster.cli import run_stage

    root = tmp_path_factory.mktemp("fuzz")
    cat = run_stage({"n_stars": 40, "epochs": [0.0, 10.0]}, root / "catalogue.h5", seed=1)
    data = Path(cat).read_bytes()
    (root / "empty.h5").write_bytes(b"")
    (root / "folder.h5").mkdir()
    (root / "text.h5").write_text("this is not a product\n")
    (root / "binary.h5").write_bytes(bytes(range(256)) * 64)
    (root / "truncated.h5").write_bytes(data[: len(data) // 2])
    shutil.copy(cat, root / "nan.h5")
    with h5py.File(root / "nan.h5", "r+") as f:
        for _name, obj in _datasets(f):
            if not obj.size:
                continue
            values = obj[()]
            if obj.dtype.kind == "f":
                values.flat[0] = np.nan
                values.flat[-1] = np.inf
            elif obj.dtype.names:  # a table (compound dataset): every float column
                for field in obj.dtype.names:
                    if obj.dtype[field].kind == "f":
                        values[field][0] = np.nan
                        values[field][-1] = np.inf
            else:
                continue
            obj[...] = values
    (root / "empty.toml").write_text("")
    (root / "text.toml").write_text("this = is = not toml\n[[[\n")
    (root / "binary.toml").write_bytes(b"\xff\xfe\x00junk" * 50)
    (root / "folder.toml").mkdir()
    return root


def _datasets(f):
    out = []
    f.visititems(
        lambda name, obj: out.append((name, obj)) if isinstance(obj, h5py.Dataset) else None
    )
    return out


def hostile_file(root: Path, kind: str, suffix: str = ".h5") -> Path:
    """The hostile input ``kind`` (``wrong_kind``: a valid catalogue)."""
    if kind == "missing":
        return root / f"missing{suffix}"
    if kind == "wrong_kind":
        return root / "catalogue.h5"
    if suffix == ".toml" and kind in ("truncated", "nan"):
        return root / "text.toml"
    return root / f"{kind}{suffix}"


def check_refused(capsys, argv, name: str, outputs=()):
    """Run ``mavispm argv``: exit 2, one line naming ``name``, outputs untouched."""
    before = {p: (p.read_bytes() if p.is_file() else None) for p in map(Path, outputs)}
    code = main([str(a) for a in argv])
    err = capsys.readouterr().err.strip()
    assert code == 2, (argv, code, err)
    assert err.count("\n") == 0 and "Traceback" not in err, err
    assert err.startswith("mavispm") and ": error: " in err, err
    assert name in err, (name, err)
    for path, content in before.items():
        if content is None:
            assert not path.exists(), f"{path} was created"
        else:
            assert path.read_bytes() == content, f"{path} was changed"
    return err


@pytest.fixture
def out(tmp_path) -> Path:
    return tmp_path / "out.h5"


@pytest.fixture
def existing(tmp_path) -> Path:
    path = tmp_path / "existing.h5"
    path.write_bytes(b"an earlier good product")
    return path


# ---------------------------------------------------------------- product readers


# a catalogue is the right kind for the catalogue reader: no "wrong_kind" case there
@pytest.mark.parametrize(
    ("hostile", "kind"),
    [(h, k) for k in KINDS for h in HOSTILE if not (h == "wrong_kind" and k == "catalogue")],
)
def test_product_readers_refuse_hostile_files_with_input_errors(inputs, hostile, kind):
    path = hostile_file(inputs, hostile)
    if hostile == "nan":
        # NaN in a float column is data (NaN magnitudes of undetected stars are legal);
        # the reader must still return or refuse cleanly, never crash
        try:
            read_product(path, kind)
        except MavispmError as exc:
            assert str(path) in str(exc)
        return
    with pytest.raises(MavispmError) as exc:
        read_product(path, kind)
    assert str(path.name) in str(exc.value)


def test_catalogue_reader_refuses_non_finite_positions(inputs):
    from mavispm.core.catalogue import read_catalogue

    with pytest.raises(MavispmError, match="nan.h5"):
        read_catalogue(inputs / "nan.h5")


# ---------------------------------------------------------------- file inputs of every command

#: (command, argv template): {IN} is the hostile file, {OUT} the output.
FILE_INPUTS = [
    ("frames catalogue", ["simulate", "frames", "{IN}", "-o", "{OUT}"], ".h5"),
    ("stars frames", ["measure", "stars", "{IN}", "-o", "{OUT}"], ".h5"),
    ("pm measured", ["measure", "propermotions", "{IN}", "{IN}", "-o", "{OUT}"], ".h5"),
    ("dynamics pm", ["dynamics", "{IN}", "-o", "{OUT}", "--fast"], ".h5"),
    ("cluster config", ["simulate", "cluster", "--config", "{IN}", "-o", "{OUT}"], ".toml"),
    ("cluster input", ["simulate", "cluster", "--input", "{IN}", "-o", "{OUT}"], ".h5"),
    ("optics scene", ["simulate", "optics", "--scene", "{IN}", "-o", "{OUT}"], ".toml"),
    ("frames scene", ["simulate", "frames", "{CAT}", "--scene", "{IN}", "-o", "{OUT}"], ".toml"),
    ("stars config", ["measure", "stars", "{CAT}", "--config", "{IN}", "-o", "{OUT}"], ".toml"),
    ("stars psf prior", ["measure", "stars", "{CAT}", "--psf-prior", "{IN}", "-o", "{OUT}"], ".h5"),
    ("dynamics config", ["dynamics", "{CAT}", "--config", "{IN}", "-o", "{OUT}"], ".toml"),
    ("run workflow", ["run", "{IN}", "--workdir", "{OUTDIR}", "--dry-run"], ".toml"),
]


def _argv(template, infile, out, cat):
    return [
        a.replace("{IN}", str(infile))
        .replace("{OUT}", str(out))
        .replace("{OUTDIR}", str(out.parent / "work"))
        .replace("{CAT}", str(cat))
        for a in template
    ]


def _applies(hostile: str, label: str, suffix: str) -> bool:
    """A catalogue is a valid star list and TOML inputs have no product kind; an empty
    TOML file is valid (all settings at their defaults)."""
    if hostile == "wrong_kind" and (label.startswith("cluster input") or suffix == ".toml"):
        return False
    return not (hostile == "empty" and suffix == ".toml")


@pytest.mark.parametrize(
    ("hostile", "label", "template", "suffix"),
    [(h, *f) for f in FILE_INPUTS for h in HOSTILE if _applies(h, f[0], f[2])],
    ids=[f"{f[0]}-{h}" for f in FILE_INPUTS for h in HOSTILE if _applies(h, f[0], f[2])],
)
def test_hostile_input_files(inputs, capsys, out, existing, hostile, label, template, suffix):
    infile = hostile_file(inputs, hostile, suffix)
    for target in (out, existing):
        argv = _argv(template, infile, target, inputs / "catalogue.h5")
        check_refused(capsys, argv, infile.name, outputs=[target])


# ---------------------------------------------------------------- outputs and options


OUTPUT_COMMANDS = [
    ["simulate", "cluster", "--n-stars", "20"],
    ["measure", "propermotions", "{CAT}", "{CAT}"],
]


@pytest.mark.parametrize("cmd", OUTPUT_COMMANDS, ids=["cluster", "propermotions"])
def test_output_at_a_folder_or_below_a_file(inputs, capsys, tmp_path, cmd):
    argv = [a.replace("{CAT}", str(inputs / "catalogue.h5")) for a in cmd]
    folder = tmp_path / "a_folder"
    folder.mkdir()
    if cmd[1] == "cluster":
        check_refused(capsys, [*argv, "-o", folder], "a_folder")
        assert list(folder.iterdir()) == []
        blocker = tmp_path / "plain_file"
        blocker.write_text("x")
        check_refused(capsys, [*argv, "-o", blocker / "out.h5"], "plain_file")
        assert blocker.read_text() == "x"


@pytest.mark.parametrize(
    ("argv", "option"),
    [
        (["simulate", "cluster", "-o", "{OUT}", "--seed", "-1"], "--seed"),
        (["simulate", "cluster", "-o", "{OUT}", "--seed", "x"], "--seed"),
        (["simulate", "cluster", "-o", "{OUT}", "--n-stars", "0"], "--n-stars"),
        (["simulate", "cluster", "-o", "{OUT}", "--n-stars", "1e9"], "--n-stars"),
        (["simulate", "cluster", "-o", "{OUT}", "--n-stars", "1000000000"], "--n-stars"),
        (["simulate", "cluster", "-o", "{OUT}", "--epochs", "a,b"], "--epochs"),
        (["simulate", "cluster", "-o", "{OUT}", "--tracer", "cube"], "--tracer"),
        (["simulate", "frames", "{CAT}", "-o", "{OUT}", "--seed", "-1"], "--seed"),
        (["measure", "stars", "{CAT}", "-o", "{OUT}", "--seed", "-5"], "--seed"),
        (["measure", "propermotions", "{CAT}", "{CAT}", "-o", "{OUT}", "--order", "7"], "--order"),
        (["dynamics", "{CAT}", "-o", "{OUT}", "--seed", "-1"], "--seed"),
        (["run", "quickstart", "--workers", "-1", "--dry-run"], "--workers"),
        (["run", "quickstart", "--set", "nokey", "--dry-run"], "--set"),
        (["cache", "--max-size", "-1GB"], "--max-size"),
        (["nonsense-command"], "nonsense-command"),
    ],
)
def test_bad_option_values_are_usage_errors(inputs, capsys, out, argv, option):
    argv = [
        a.replace("{OUT}", str(out)).replace("{CAT}", str(inputs / "catalogue.h5")) for a in argv
    ]
    check_refused(capsys, argv, option, outputs=[out])


# a catalogue is the right kind for a workflow's catalogue path: no "wrong_kind" case
@pytest.mark.parametrize("hostile", [h for h in HOSTILE if h != "wrong_kind"])
def test_workflow_catalogue_path_to_hostile_files(inputs, capsys, tmp_path, hostile):
    infile = hostile_file(inputs, hostile)
    wf = tmp_path / "wf.toml"
    wf.write_text(
        f'[workflow]\nname = "w"\n[catalogue]\npath = "{infile}"\n[epochs]\ntimes = [0]\n'
    )
    workdir = tmp_path / "work"
    check_refused(capsys, ["run", wf, "--workdir", workdir, "--dry-run"], infile.name)
    assert not workdir.exists()


def test_workdir_at_a_file(inputs, capsys, tmp_path):
    blocker = tmp_path / "not_a_dir"
    blocker.write_text("x")
    check_refused(capsys, ["run", "quickstart", "--workdir", blocker, "--dry-run"], "--workdir")
    check_refused(
        capsys, ["run", "quickstart", "--workdir", blocker / "below", "--dry-run"], "not_a_dir"
    )
    assert blocker.read_text() == "x"


@pytest.mark.parametrize("hostile", ["missing", "empty", "text", "binary", "folder"])
def test_report_of_hostile_run_directories(inputs, capsys, tmp_path, hostile):
    rundir = tmp_path / "run"
    if hostile != "missing":
        rundir.mkdir()
        src = hostile_file(inputs, hostile, ".h5")
        target = rundir / "summary.json"
        if hostile == "folder":
            target.mkdir()
        elif hostile != "empty":
            shutil.copy(src, target)
        else:
            target.write_text("")
    check_refused(capsys, ["report", rundir], "run", outputs=[rundir / "report.md"])


# ---------------------------------------------------------------- slow: frames and measured


@pytest.fixture(scope="module")
def rendered(inputs):
    """A small frames product and its measurement (slow: renders one frame)."""
    from mavispm.measure.stars.cli import run_stage as measure
    from mavispm.simulate.cluster.cli import run_stage as cluster
    from mavispm.simulate.render.cli import run_stage as render

    cat = cluster({"n_stars": 400, "epochs": [0.0]}, inputs / "dense.h5", seed=3)
    scene = {"detector": {"nx": 1200, "ny": 1200}, "optics": {"psf": {"n_nodes": 3}}}
    frames = render(cat, "e0", scene, inputs / "frames.h5", seed=1)
    measured = measure(frames, {}, inputs / "measured.h5", seed=1)
    return Path(frames), Path(measured)


def _poison(src: Path, dst: Path, value: float) -> Path:
    shutil.copy(src, dst)
    with h5py.File(dst, "r+") as f:
        for _, obj in _datasets(f):
            if obj.dtype.kind == "f" and obj.ndim == 2 and obj.size > 100:  # the image
                obj[...] = value
    return dst


@pytest.mark.slow
@pytest.mark.parametrize("value", [np.nan, 0.0, 1e30])
def test_hostile_images_are_refused_naming_the_file_and_cause(
    inputs, rendered, capsys, tmp_path, value
):
    frames, _ = rendered
    bad = _poison(frames, tmp_path / "bad_frames.h5", value)
    out = tmp_path / "m.h5"
    err = check_refused(capsys, ["measure", "stars", bad, "-o", out], "bad_frames.h5", [out])
    assert any(w in err for w in ("NaN", "constant", "saturated")), err


@pytest.mark.slow
@pytest.mark.parametrize("hostile", ["truncated", "wrong_kind"])
def test_hostile_measured_products(inputs, rendered, capsys, tmp_path, hostile):
    frames, measured = rendered
    data = measured.read_bytes()
    bad = tmp_path / f"{hostile}_measured.h5"
    if hostile == "truncated":
        bad.write_bytes(data[: len(data) // 2])
    else:
        shutil.copy(frames, bad)
    out = tmp_path / "pm.h5"
    check_refused(capsys, ["measure", "propermotions", measured, bad, "-o", out], bad.name, [out])
