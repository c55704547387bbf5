"""Small, real, seeded stand-in stages for testing the workflow runner.

Each stage does genuine (tiny) seeded work and writes a product in the format
of docs/formats.md with :func:`mavispm.core.products.write_product`, so caching,
resumption, executors and reports are tested on real files without waiting for
the science stages.

Environment switches (read inside the stage, so they also reach workers):

``WF_TEST_LOG``
    A file each stage call appends ``"<stage> <node detail>"`` to.
``WF_TEST_FAIL``
    A stage name: that stage raises ``RuntimeError``.
``WF_TEST_KILL``
    A stage name: that stage writes a partial file, then kills its own process
    with SIGKILL (a power cut in the middle of a stage).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import astropy.units as u
import numpy as np
from astropy.table import QTable

from mavispm.core.catalogue import read_catalogue, write_catalogue
from mavispm.core.config import from_mapping, unit_field
from mavispm.core.products import read_product, write_product
from mavispm.workflows.registry import StageRegistry, StageSpec

_MOD = "workflows_helpers"

#: Node ids of a one-scene, two-epoch workflow with every stage.
ALL_NODES = frozenset(
    {
        "cluster",
        "optics/main",
        "frames/main/e0",
        "frames/main/e1",
        "stars/main/e0",
        "stars/main/e1",
        "propermotions/main",
        "dynamics/main",
    }
)


# ------------------------------------------------------------------ settings


@dataclass(frozen=True)
class ClusterSettings:
    n_stars: int = 150
    sigma_pm: float = unit_field(0.3, "mas/yr")
    imbh_mass: float = unit_field(0.0, "solMass")
    size: float = unit_field(8.0, "arcsec")
    epochs: tuple[float, ...] = ()


@dataclass(frozen=True)
class OpticsSettings:
    fwhm: float = unit_field(18.0, "mas")


@dataclass(frozen=True)
class SceneSettings:
    jitter: float = unit_field(0.05, "mas")
    pixel_scale: float = unit_field(7.5, "mas")
    exptime: float = unit_field(30.0, "s")
    optics: dict = field(default_factory=dict)


@dataclass(frozen=True)
class MeasureSettings:
    noise: float = unit_field(0.1, "mas")


@dataclass(frozen=True)
class PMSettings:
    clip: float = 5.0


@dataclass(frozen=True)
class DynamicsSettings:
    per_bin: int = 30
    n_boot: int = 20


def _validator(cls):
    def validate(settings, source=None):
        return from_mapping(cls, settings, source=source)

    return validate


validate_cluster = _validator(ClusterSettings)
validate_optics = _validator(OpticsSettings)
validate_scene = _validator(SceneSettings)
validate_measure = _validator(MeasureSettings)
validate_pm = _validator(PMSettings)
validate_dynamics = _validator(DynamicsSettings)


def _hooks(stage: str, detail: str, outdir: Path) -> None:
    log = os.environ.get("WF_TEST_LOG")
    if log:
        with open(log, "a") as fh:
            fh.write(f"{stage} {detail}\n")
    if os.environ.get("WF_TEST_WARN") == stage:
        warnings.warn(f"injected warning in {stage}", UserWarning, stacklevel=2)
    if os.environ.get("WF_TEST_FAIL") == stage:
        raise RuntimeError(f"injected failure in {stage}")
    if os.environ.get("WF_TEST_KILL") == stage:
        (outdir / "half_written.tmp").write_bytes(b"\0" * 1000)
        os.kill(os.getpid(), signal.SIGKILL)
    once = outdir / "killed_once"
    if os.environ.get("WF_TEST_KILL_ONCE") == stage and not once.exists():
        once.write_text("")  # the retry (another worker) finds it and goes on
        os.kill(os.getpid(), signal.SIGKILL)


# ------------------------------------------------------------------ stages


def run_cluster(inputs, settings, params, seed, outdir):
    s = validate_cluster(settings)
    _hooks("cluster", "", outdir)
    rng = np.random.default_rng(seed)
    n = s.n_stars
    x0 = rng.uniform(-s.size / 2, s.size / 2, n)
    y0 = rng.uniform(-s.size / 2, s.size / 2, n)
    r = np.hypot(x0, y0) + 0.3
    boost = 1.0 + s.imbh_mass / 1000.0 / r  # a toy central cusp in the velocity dispersion
    pmx = rng.normal(0, s.sigma_pm, n) * boost
    pmy = rng.normal(0, s.sigma_pm, n) * boost
    mag = rng.uniform(14.0, 27.0, n)
    epochs = {}
    for name, t in params["epochs"]:
        tab = QTable()
        tab["id"] = np.arange(n, dtype=np.int64)
        tab["x"] = (x0 + pmx * t / 1000.0) * u.arcsec
        tab["y"] = (y0 + pmy * t / 1000.0) * u.arcsec
        tab["pm_x"] = pmx * u.mas / u.yr
        tab["pm_y"] = pmy * u.mas / u.yr
        tab["mag"] = mag * u.mag
        tab.meta["epoch"] = t * u.yr
        epochs[name] = tab
    path = write_catalogue(
        outdir / "catalogue.h5",
        epochs,
        attrs={"distance": 4.6 * u.kpc, "imbh_mass": s.imbh_mass * u.solMass},
        config=settings,
        seed=seed,
    )
    return {"main": path}


def run_optics(inputs, settings, params, seed, outdir):
    s = validate_optics(settings)
    _hooks("optics", "", outdir)
    yy, xx = np.mgrid[-7:8, -7:8] * 2.0
    sig = s.fwhm / 2.3548
    psf = np.exp(-0.5 * (xx**2 + yy**2) / sig**2)
    path = write_product(
        outdir / "psfgrid.h5",
        "psfgrid",
        arrays={"psf": psf / psf.sum()},
        attrs={"fwhm": s.fwhm * u.mas},
        config=settings,
    )
    return {"main": path}


def run_frames(inputs, settings, params, seed, outdir):
    s = validate_scene(settings)
    _hooks("frames", f"{params['scene']}/{params['epoch']}", outdir)
    cat = read_catalogue(inputs["catalogue"])
    tab = cat.epochs[params["epoch"]]
    fwhm = 18.0
    if "psf" in inputs:
        fwhm = read_product(inputs["psf"], "psfgrid").attrs["fwhm"].to_value(u.mas)
    rng = np.random.default_rng(seed)
    n = len(tab)
    x = tab["x"].to_value(u.arcsec) + rng.normal(0, s.jitter, n) / 1000.0
    y = tab["y"].to_value(u.arcsec) + rng.normal(0, s.jitter, n) / 1000.0
    flux = 10 ** (-0.4 * (tab["mag"].to_value(u.mag) - 25.0)) * 1000.0 * s.exptime / 30.0
    nx = 64
    scale = 8000.0 / nx  # mas per pixel of this toy image
    image = np.histogram2d(
        y * 1000 / scale, x * 1000 / scale, bins=nx, range=[[-nx / 2, nx / 2]] * 2, weights=flux
    )[0]
    image = rng.poisson(image + 10.0).astype(np.float32)
    truth = QTable()
    truth["id"] = tab["id"]
    truth["x_pix"] = x * 1000 / s.pixel_scale
    truth["y_pix"] = y * 1000 / s.pixel_scale
    truth["x"] = x * u.arcsec
    truth["y"] = y * u.arcsec
    truth["x_cat"] = tab["x"]
    truth["y_cat"] = tab["y"]
    truth["flux"] = flux * u.electron
    truth["mag"] = tab["mag"]
    attrs = {
        "epoch": u.Quantity(tab.meta["epoch"], u.yr),
        "pixel_scale": s.pixel_scale * u.mas,
        "exptime": s.exptime * u.s,
        "fwhm": fwhm * u.mas,
        "scene": settings,
    }
    path = write_product(
        outdir / "frames.h5",
        "frames",
        tables={"truth": truth},
        arrays={"image": image},
        attrs=attrs,
        config=settings,
        seed=seed,
    )
    products = {"main": path}
    if params.get("fits"):
        from astropy.io import fits

        from mavispm.core.atomic import atomic_path

        with atomic_path(outdir / "frames.fits") as tmp:
            hdr = fits.Header(
                {"MVEPOCH": float(attrs["epoch"].value), "PIXSCALE": s.pixel_scale / 1000}
            )
            fits.PrimaryHDU(image, header=hdr).writeto(tmp, output_verify="silentfix")
        products["fits"] = outdir / "frames.fits"
    return products


def run_stars(inputs, settings, params, seed, outdir):
    s = validate_measure(settings)
    _hooks("stars", params["epoch"], outdir)
    prod = read_product(inputs["frames"], "frames")
    truth = prod.tables["truth"]
    fwhm = prod.attrs["fwhm"].to_value(u.mas)
    rng = np.random.default_rng(seed)
    n = len(truth)
    mag = truth["mag"].to_value(u.mag)
    err = s.noise * fwhm / 18.0 * (1.0 + 10 ** (0.4 * (mag - 22.0))) / 1000.0  # arcsec
    detected = mag < 26.5
    x = truth["x"].to_value(u.arcsec) + rng.normal(0, 1, n) * err
    y = truth["y"].to_value(u.arcsec) + rng.normal(0, 1, n) * err
    stars = QTable()
    stars["id"] = truth["id"][detected]
    for name, val in (("x", x), ("y", y), ("x_err", err), ("y_err", err)):
        stars[name] = val[detected] * u.arcsec
    stars["x_pix"] = stars["x"].to_value(u.mas) / prod.attrs["pixel_scale"].to_value(u.mas)
    stars["y_pix"] = stars["y"].to_value(u.mas) / prod.attrs["pixel_scale"].to_value(u.mas)
    stars["flux"] = truth["flux"][detected]
    stars["flux_err"] = np.sqrt(truth["flux"][detected].value) * u.electron
    stars["sky"] = np.full(int(detected.sum()), 10.0) * u.electron
    stars["chi2"] = np.ones(int(detected.sum()))
    stars["flag"] = np.zeros(int(detected.sum()), dtype=np.int64)
    stars["x_true"] = truth["x"][detected]
    stars["y_true"] = truth["y"][detected]
    stars["mag"] = truth["mag"][detected]
    stars["match_dist"] = np.hypot(stars["x"] - stars["x_true"], stars["y"] - stars["y_true"])
    path = write_product(
        outdir / "measured.h5",
        "measured",
        tables={"stars": stars},
        attrs={"epoch": prod.attrs["epoch"], "engine": "toy"},
        config=settings,
        seed=seed,
    )
    return {"main": path}


def run_propermotions(inputs, settings, params, seed, outdir):
    validate_pm(settings)
    _hooks("propermotions", str(len(inputs["measured"])), outdir)
    prods = [read_product(p, "measured") for p in inputs["measured"]]
    times = np.array([p.attrs["epoch"].to_value(u.yr) for p in prods])
    common = set(prods[0].tables["stars"]["id"])
    for p in prods[1:]:
        common &= set(p.tables["stars"]["id"])
    ids = np.array(sorted(common), dtype=np.int64)

    def column(p, name):
        t = p.tables["stars"]
        order = {int(i): k for k, i in enumerate(t["id"])}
        return np.array([t[name][order[int(i)]].to_value(u.arcsec) for i in ids])

    dt = times[-1] - times[0]
    out = QTable()
    out["id"] = ids
    first, last = prods[0], prods[-1]
    out["x"] = column(first, "x") * u.arcsec
    out["y"] = column(first, "y") * u.arcsec
    out["R"] = np.hypot(out["x"], out["y"])
    pmx = (column(last, "x") - column(first, "x")) / dt * 1000.0
    pmy = (column(last, "y") - column(first, "y")) / dt * 1000.0
    err = np.sqrt(column(first, "x_err") ** 2 + column(last, "x_err") ** 2) / dt * 1000.0
    out["pm_x"] = pmx * u.mas / u.yr
    out["pm_y"] = pmy * u.mas / u.yr
    out["pm_x_err"] = err * u.mas / u.yr
    out["pm_y_err"] = err * u.mas / u.yr
    out["pm_x_true"] = (
        (column(last, "x_true") - column(first, "x_true")) / dt * 1000.0 * u.mas / u.yr
    )
    out["pm_y_true"] = (
        (column(last, "y_true") - column(first, "y_true")) / dt * 1000.0 * u.mas / u.yr
    )
    t0 = first.tables["stars"]
    order = {int(i): k for k, i in enumerate(t0["id"])}
    out["mag"] = [t0["mag"][order[int(i)]].to_value(u.mag) for i in ids] * u.mag
    out["n_epochs"] = np.full(len(ids), len(prods))
    out["flag"] = np.zeros(len(ids), dtype=np.int64)
    path = write_product(
        outdir / "propermotions.h5",
        "propermotions",
        tables={"stars": out},
        attrs={"epochs": times * u.yr, "distance": 4.6 * u.kpc},
        config=settings,
    )
    return {"main": path}


def run_dynamics(inputs, settings, params, seed, outdir):
    s = validate_dynamics(settings)
    _hooks("dynamics", "", outdir)
    stars = read_product(inputs["propermotions"], "propermotions").tables["stars"]
    rng = np.random.default_rng(seed)
    order = np.argsort(stars["R"].value)
    pm = np.concatenate(
        [stars["pm_x"].value[order[: s.per_bin]], stars["pm_y"].value[order[: s.per_bin]]]
    )
    boot = [rng.choice(pm, pm.size).std() for _ in range(s.n_boot)]
    inner = float(np.mean(boot))
    outer = float(
        np.std(
            np.concatenate(
                [stars["pm_x"].value[order[s.per_bin :]], stars["pm_y"].value[order[s.per_bin :]]]
            )
        )
    )
    profile = QTable({"r": [1.0, 2.0] * u.arcsec, "sigma": [inner, outer] * u.mas / u.yr})
    attrs = {
        "ln_bayes_factor": float(np.log(inner / outer) * 10),
        "sigma_inner": inner * u.mas / u.yr,
        "distance": 4.6 * u.kpc,  # the same at every sweep point
    }
    path = write_product(
        outdir / "dynamics.h5",
        "dynamics",
        tables={"profile": profile},
        attrs=attrs,
        config=settings,
        seed=seed,
    )
    products = {"main": path}
    if params.get("plots"):
        import matplotlib.pyplot as plt

        from mavispm.core.atomic import atomic_path

        fig, ax = plt.subplots()
        ax.plot([1, 2], [inner, outer], "o-")
        with atomic_path(outdir / "profile.png") as tmp:
            fig.savefig(tmp, format="png")
        plt.close(fig)
        products["plot_profile"] = outdir / "profile.png"
    return products


def write_report_measured(paths, outdir):
    """A stage report: star counts per product (Markdown)."""
    from mavispm.core.atomic import atomic_path

    outdir.mkdir(parents=True, exist_ok=True)
    lines = ["| product | stars |", "|---|---|"]
    for p in paths:
        lines.append(
            f"| {Path(p).parent.name} | {len(read_product(p, 'measured').tables['stars'])} |"
        )
    with atomic_path(outdir / "counts.md") as tmp:
        tmp.write_text("\n".join(lines) + "\n")
    return [outdir / "counts.md"]


def stand_in_registry() -> StageRegistry:
    """Registry of the stand-in stages under the real stage names."""
    validators = {
        "cluster": "validate_cluster",
        "optics": "validate_optics",
        "frames": "validate_scene",
        "stars": "validate_measure",
        "propermotions": "validate_pm",
        "dynamics": "validate_dynamics",
    }
    specs = [
        StageSpec(
            name=name,
            run=f"{_MOD}:run_{name}",
            validate=f"{_MOD}:{val}",
            summarize="mavispm.workflows.stages:product_metrics",
            report=f"{_MOD}:write_report_measured" if name == "stars" else None,
            version="test",
        )
        for name, val in validators.items()
    ]
    return StageRegistry.of(specs)


TINY_WORKFLOW = """\
[workflow]
name = "tiny"
seed = 7

[cluster]
n_stars = 150

[epochs]
times = [0, 5]

[scene]
jitter = "0.05 mas"

[scene.optics]
fwhm = "18 mas"

[measure]
noise = "0.1 mas"

[propermotions]

[dynamics]
per_bin = 30

[outputs]
report = false
plots = false
fits = false
"""

#: Outputs table asking for the full report (plots, FITS, all recipes).
REPORT_OUTPUTS = """\
[outputs]
fits = true
tables = ["astrometry_by_magnitude", "pm_accuracy", "dispersion_profiles", "model_comparison"]
"""


def with_report(text: str = TINY_WORKFLOW) -> str:
    """The workflow text with the full report switched on."""
    return text[: text.index("[outputs]")] + REPORT_OUTPUTS


def write_workflow(folder: Path, text: str = TINY_WORKFLOW, name: str = "tiny.toml") -> Path:
    """Write a workflow file and return its path."""
    path = Path(folder) / name
    path.write_text(textwrap.dedent(text))
    return path


def read_log(path: Path) -> list[str]:
    """Lines of the stage-call log (empty when missing)."""
    return Path(path).read_text().splitlines() if Path(path).exists() else []


def fingerprints(rundir: Path, ignore: tuple[str, ...] = ()) -> dict[str, str]:
    """Content fingerprint of every HDF5 product in a run directory."""
    from mavispm.workflows.cache import product_fingerprint

    return {
        str(p.relative_to(rundir)): product_fingerprint(p, ignore)
        for p in sorted((Path(rundir) / "products").rglob("*.h5"))
    }


def start_subprocess(
    workflow: Path, workdir: Path, env: dict, scheduler: str = "serial"
) -> subprocess.Popen:
    """Start a workflow run with the stand-in registry in a child Python process."""
    here = Path(__file__).resolve().parent
    code = textwrap.dedent(
        f"""
        import sys
        sys.path.insert(0, {str(here)!r})
        from workflows_helpers import stand_in_registry
        from mavispm.workflows.runner import run_workflow
        run_workflow({str(workflow)!r}, workdir={str(workdir)!r}, scheduler={scheduler!r},
                     registry=stand_in_registry(), progress=False)
        """
    )
    return subprocess.Popen(
        [sys.executable, "-c", code],
        env={**os.environ, **env},
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def run_in_subprocess(workflow: Path, workdir: Path, env: dict, scheduler: str = "serial"):
    """Run a workflow in a child process; return (returncode, stderr)."""
    proc = start_subprocess(workflow, workdir, env, scheduler)
    _, err = proc.communicate(timeout=120)
    return proc.returncode, err
