"""Colour-dependent shifts in the run report (workflows/colour_report.py), end to end.

A tiny field rendered with refraction (broadband slices) at two zenith angles, measured
and turned into proper motions; the ``colour_shifts`` recipe must show, per
temperature bin, measured position and PM shifts that follow the true DAR shift
computed independently here from the refraction module's quadrature-checked means.
"""

from __future__ import annotations

import csv
import textwrap

import numpy as np

from mavispm.workflows.config import load_workflow
from mavispm.workflows.runner import run_workflow

TINY = """
[workflow]
name = "tiny_colour"
seed = 5
executor = "serial"

[cluster]
preset = "ngc3201"
imbh_mass = 0
n_stars = 80
field_size = "1.2 arcsec"

[epochs]
times = [0, 10]

[scene]
exptime = "30 s"
nexp = 4

[scene.detector]
nx = 180
ny = 180

[scene.render]
halo = false

[scene.optics.psf]
mode = "diffraction"
n_nodes = 1
stamp_size = "0.3 arcsec"
pixel_scale = "3.75 mas"
pupil_sampling = 32
psd_padding = 2.5

[scene.optics.halo]
enabled = false

[scene.optics.tiptilt]
enabled = false

[scene.optics.distortion]
enabled = false

[scene.optics.refraction]
enabled = true
adc_residual = 0.1
epochs = [[0, 10, 0], [10, 40, 0]]

[scene.optics.broadband]
slices = 2
colour_bins = 3

[measure]
engine = "fast"
psf_variation = "constant"

[propermotions]
order = 1

[outputs]
fits = false
plots = false
tables = ["colour_shifts"]
"""


def _rows(path):
    with open(path) as fh:
        return list(csv.DictReader(fh))


def test_report_shows_colour_dependent_shifts(tmp_path):
    path = tmp_path / "wf.toml"
    path.write_text(textwrap.dedent(TINY))
    result = run_workflow(load_workflow(path), workdir=tmp_path / "work", progress=False)
    optics_dir = result.product("optics/main").parent
    assert len(list(optics_dir.glob("psfgrid-*.h5"))) == 3  # the grid and two slices
    rundir = result.rundir
    report = (rundir / "report.md").read_text()
    assert "against colour" in report
    rows = _rows(rundir / "report" / "colour_shifts.csv")
    pm_x = [r for r in rows if r["quantity"].startswith("PM") and r["axis"] == "x"]
    pos = [r for r in rows if r["quantity"].startswith("position e1") and r["axis"] == "x"]
    used = [r for r in pm_x if int(r["n"]) >= 5]
    assert len(used) >= 2  # at least two well-populated colour bins
    true = np.array([float(r["true"]) for r in used])
    meas = np.array([float(r["median"]) for r in used])
    # zenith 10 -> 50 deg along +x with 30% of the dispersion: the bins' true DAR
    # changes differ by tens of microarcsec/yr, and the measured PMs follow them
    assert np.ptp(true) > 20
    assert np.allclose(meas, true, atol=0.15 * np.ptp(true) + 5)
    # single epoch (z = 50 deg): measured minus catalogue positions follow the DAR shift
    used = [r for r in pos if int(r["n"]) >= 5]
    t = np.array([float(r["true"]) for r in used])
    m = np.array([float(r["median"]) for r in used])
    assert np.ptp(t) > 200  # microarcsec
    assert np.allclose(m, t, atol=0.15 * np.ptp(t))
    # y is across the zenith: no colour shift
    ty = [float(r["true"]) for r in rows if r["quantity"].startswith("PM") and r["axis"] == "y"]
    assert np.nanmax(np.abs(ty)) < 1e-6
