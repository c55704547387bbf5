"""Run reports: report.md with tables and plots, from a run directory alone.

:func:`write_report` reads ``summary.json`` and the products of a run
directory and writes ``report.md`` plus its tables and PNG plots under
``report/``. ``mavispm report RUNDIR`` calls it, so a report can be redrawn
without running any stage.

Sections: stage timings (ran / cached / wall time), per-node status, the sweep
table and plots, the report *recipes* a workflow asks for in
``[outputs] tables`` (:data:`RECIPES`), and each stage's own accuracy report
(``write_report`` of the stage module) per study, sweep point and scene.

Recipes
-------
``astrometry_by_magnitude``
    The paper's tab:simresults: x-position dispersion (three iterations of
    2-sigma clipping) in the paper's magnitude bins, one row per scene, with
    star counts, the recovered fractions of tab:simparams and residual plots.
``pm_accuracy``
    Proper-motion error against magnitude (and radius): robust RMS, fraction of
    stars within 50 and 150 microarcsec/yr per magnitude bin, per variant.
``dispersion_profiles``
    PM dispersion profiles in equal-count radial bins (default 300 stars),
    measured and true, for every study on one plot (paper fig:imbhresults).
``model_comparison``
    The dynamics stage's model-comparison numbers (ln B, Delta ln L, AIC,
    BIC, M_BH) per study and sweep point, with the injected IMBH mass of a
    simulated cluster (its catalogue's ``imbh_mass``) beside the fitted one.
``colour_shifts``
    Scenes rendered with atmospheric refraction: median signed position error per
    epoch and PM error per effective-temperature bin, measured next to the true DAR
    shift (:mod:`mavispm.workflows.colour_report`).
``fast_stars``
    The fast-star test per study and sweep point: significant fast stars, the
    expected false ones, the lower IMBH mass limit (with ln B), the fast stars
    themselves, and against the swept parameters a plot.
"""

from __future__ import annotations

import json
import math
import os
import re
import warnings
from collections.abc import Callable, Mapping
from pathlib import Path

import numpy as np
from astropy.stats import mad_std

from mavispm.core.atomic import atomic_path
from mavispm.core.errors import InputError, MavispmError
from mavispm.core.paths import NAME_PATTERN, contained

__all__ = [
    "astrometry_by_magnitude",
    "BAD_FLAGS",
    "bin_label",
    "clipped_dispersion",
    "colour_shifts",
    "dispersion_profile",
    "dispersion_profiles",
    "KEY_DYNAMICS_METRICS",
    "model_comparison",
    "nest_headings",
    "panel_title",
    "PAPER_BINS",
    "pm_accuracy",
    "read_summary",
    "RECIPE_TITLES",
    "RECIPES",
    "warnings_section",
    "write_report",
]

#: Magnitude bins of the paper's tab:simresults (lower, upper).
PAPER_BINS = (
    (-math.inf, 16.0),
    (16.0, 17.0),
    (17.0, 18.0),
    (18.0, 19.0),
    (19.0, 20.0),
    (20.0, 22.0),
    (22.0, 24.0),
    (24.0, 26.0),
    (26.0, math.inf),
)
#: Measured-star flags that mean "no usable position" (not converged, no match, failed).
BAD_FLAGS = 1 | 16 | 32


def read_summary(rundir: str | os.PathLike) -> dict:
    """Read and check a run directory's summary.json.

    The file is data: its structure is checked (:func:`check_summary`) and
    nothing in it is ever imported or executed.

    Parameters
    ----------
    rundir : str or os.PathLike
        A run directory.

    Returns
    -------
    dict
        The parsed ``summary.json``.

    Raises
    ------
    InputError
        When the folder is not a mavispm run directory or summary.json is malformed.
    """
    path = Path(rundir) / "summary.json"
    if not path.is_file():
        raise InputError("not a mavispm run directory (no summary.json)", path=rundir)
    try:
        summary = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"summary.json is not valid JSON ({exc})", path=path) from None
    check_summary(summary, path)
    return summary


def check_summary(summary: object, path: str | os.PathLike) -> None:
    """Check the structure of a summary.json mapping (see docs/workflows.md).

    Parameters
    ----------
    summary : object
        The parsed ``summary.json``.
    path : pathlib.Path or str
        The file, named in errors.

    Raises
    ------
    InputError
        Naming the file and the first entry that is not as expected.
    """

    def fail(what: str):
        raise InputError(f"malformed summary.json: {what}", path=path)

    if not isinstance(summary, dict):
        fail(f"expected a JSON object, got {type(summary).__name__}")
    for key, kind in (("workflow", str), ("nodes", list), ("stages", dict)):
        if not isinstance(summary.get(key), kind):
            fail(f"expected '{key}' to be a {kind.__name__}")
    for i, node in enumerate(summary["nodes"]):
        if not isinstance(node, dict):
            fail(f"nodes[{i}] is not an object")
        for key, kind in (
            ("id", str),
            ("stage", str),
            ("status", str),
            ("products", dict),
            ("labels", dict),
        ):
            if not isinstance(node.get(key), kind):
                fail(f"expected nodes[{i}].{key} to be a {kind.__name__}")
        for name, rel in node["products"].items():
            if not isinstance(rel, str):
                fail(f"expected nodes[{i}].products.{name} to be a path string")
            contained(path.parent, rel, f"summary.json nodes[{i}].products.{name}", False)
        for name, value in node["labels"].items():
            if value and (not isinstance(value, str) or not NAME_PATTERN.fullmatch(value)):
                fail(f"nodes[{i}].labels.{name} = {value!r} is not a plain name")
        if node.get("wall_s") is not None and not isinstance(node["wall_s"], (int, float)):
            fail(f"expected nodes[{i}].wall_s to be a number")
    for stage, entry in summary["stages"].items():
        if not isinstance(entry, dict) or not all(
            isinstance(entry.get(k), (int, float)) for k in ("tasks", "ran", "cached", "wall_s")
        ):
            fail(f"expected stages.{stage} to hold numbers tasks, ran, cached, wall_s")
    tables = (summary.get("outputs") or {}).get("tables", [])
    if not isinstance(tables, list):
        fail("expected outputs.tables to be a list of report recipe names")
    for recipe in tables:
        if recipe not in RECIPES:
            fail(f"unknown report recipe {recipe!r}; expected one of {sorted(RECIPES)}")
    stage_report_names(summary, path)


def bin_label(lo: float, hi: float) -> str:
    """Magnitude-bin label in the paper's style (``m<16``, ``[16,17)``, ``m>=26``).

    Parameters
    ----------
    lo, hi : float
        Bin edges [mag] (infinite for open bins).

    Returns
    -------
    str
    """
    if math.isinf(lo):
        return f"m<{hi:g}"
    if math.isinf(hi):
        return f"m>={lo:g}"
    return f"[{lo:g},{hi:g})"


def clipped_dispersion(
    values: np.ndarray, sigma: float = 2.0, iterations: int = 3
) -> tuple[float, int]:
    """Standard deviation after ``iterations`` rounds of ``sigma`` clipping about the mean
    (the paper's tab:simresults statistic; :func:`astropy.stats.sigma_clip` with
    ``cenfunc="mean", stdfunc="std"`` on values of ordinary size).

    Each round keeps the values within ``sigma`` standard deviations of the mean of the
    values kept so far and stops when none is dropped. The test is made on the
    deviations from the mean divided by their largest magnitude, so it is free of the
    values' scale and offset: astropy's clipping squares the values themselves, and for
    values near 1e-200 the squares underflow to a zero std that clips every value.

    Parameters
    ----------
    values : ndarray
        Values (any unit; non-finite ones are dropped).
    sigma : float
        Clipping threshold [standard deviations].
    iterations : int
        Maximum clipping rounds.

    Returns
    -------
    (float, int)
        Dispersion (NaN for fewer than 2 values) and the number of values kept.
    """
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    for _ in range(iterations):
        if v.size < 2:
            break
        dev = v - v.mean()
        scale = np.max(np.abs(dev))
        if scale == 0.0:  # all equal: nothing lies outside
            break
        z = dev / scale
        z -= z.mean()
        inside = z * z <= sigma**2 * np.mean(z * z)
        if inside.all():
            break
        v = v[inside]
    if v.size < 2:
        return math.nan, int(v.size)
    dev = v - v.mean()
    scale = np.max(np.abs(dev))
    std = scale * float(np.std(dev / scale)) if scale > 0 else 0.0
    return std, int(v.size)


def _nodes(summary: Mapping, stage: str) -> list[dict]:
    return [n for n in summary["nodes"] if n["stage"] == stage and n.get("products")]


def _variant_label(node: Mapping) -> str:
    lab = node["labels"]
    return " ".join(p for p in (lab.get("study"), lab.get("point")) if p) or "-"


def panel_title(node: Mapping, keys: tuple[str, ...] = ("study", "point", "scene", "epoch")) -> str:
    """A node's labels spelled out for a plot title or legend.

    Parameters
    ----------
    node : mapping
        A node of ``summary.json`` (its ``labels``: study, point, scene, epoch).
    keys : tuple of str
        Labels to name, in order.

    Returns
    -------
    str
        For example "study imbh, mass=1500, scene main, epoch e1" (labels absent
        from the node are left out).
    """
    lab = node["labels"]
    names = {"study": "study", "point": "", "scene": "scene", "epoch": "epoch"}
    parts = [f"{names[k]} {lab[k]}".strip() for k in keys if lab.get(k)]
    return ", ".join(parts) or "run"


def _read_table(path: Path, kind: str, table: str):
    from mavispm.core.products import read_product

    return read_product(path, kind, load_arrays=False).tables[table]


def _q(table, name: str, unit: str) -> np.ndarray:
    col = table[name]
    if hasattr(col, "to_value"):
        return np.asarray(col.to_value(unit), dtype=float)
    return np.asarray(col, dtype=float)


def _md_table(header: list[str], rows: list[list]) -> str:
    out = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    out += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(out) + "\n"


def _save(fig, path: Path) -> Path:
    import matplotlib.pyplot as plt

    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=100)
    plt.close(fig)
    return path


def _rel(path: Path, rundir: Path) -> str:
    return os.path.relpath(path, rundir)


# --------------------------------------------------------------------------- recipes


def astrometry_by_magnitude(summary: Mapping, rundir: Path, outdir: Path) -> str:
    """Recipe: the paper's per-magnitude astrometric dispersion table (tab:simresults).

    Parameters
    ----------
    summary : mapping
        The run's ``summary.json``.
    rundir : pathlib.Path
        The run directory.
    outdir : pathlib.Path
        Where the section's CSV and PNG files go (``report/``).

    Returns
    -------
    str
        The Markdown section.
    """
    import matplotlib.pyplot as plt

    nodes = _nodes(summary, "stars")
    if not nodes:
        return "No measured stars in this run.\n"
    frames_by_id = {n["id"]: n for n in _nodes(summary, "frames")}
    header = ["variant", "scene", "epoch"] + [bin_label(*b) + " [uas]" for b in PAPER_BINS]
    header += ["recovered m<22", "recovered m>=22", "sigma_TT,ave [mas]"]
    rows, csv_rows = [], []
    fig, axes = plt.subplots(len(nodes), 1, figsize=(7, 2.2 * len(nodes) + 0.6), squeeze=False)
    for ax, node in zip(axes[:, 0], nodes):
        stars = _read_table(rundir / node["products"]["main"], "measured", "stars")
        mag = _q(stars, "mag", "mag")
        dx = (_q(stars, "x", "arcsec") - _q(stars, "x_true", "arcsec")) * 1e6
        good = np.isfinite(dx) & np.isfinite(mag)
        if "flag" in stars.colnames:
            good &= (np.asarray(stars["flag"]).astype(int) & BAD_FLAGS) == 0
        cells, csv = [], []
        for lo, hi in PAPER_BINS:
            sel = good & (mag >= lo) & (mag < hi)
            disp, kept = clipped_dispersion(dx[sel])
            cells.append("-" if not math.isfinite(disp) else f"{disp:.2f} ({kept})")
            csv += [disp, kept]
        frames_node = frames_by_id.get(node["id"].replace("stars/", "frames/", 1))
        frac = _recovered(frames_node, rundir, mag[good])
        cells += [f"{100 * f:.0f}%" if math.isfinite(f) else "-" for f in frac]
        sigma_tt = _sigma_tt(frames_node, rundir)
        cells.append(f"{sigma_tt:.2f}" if math.isfinite(sigma_tt) else "-")
        frac = [*frac, sigma_tt]
        lab = node["labels"]
        rows.append([_variant_label(node), lab.get("scene", ""), lab.get("epoch", ""), *cells])
        csv_rows.append(
            [_variant_label(node), lab.get("scene", ""), lab.get("epoch", ""), *csv, *frac]
        )
        _residual_panel(ax, mag[good], dx[good], panel_title(node))
    axes[-1, 0].set_xlabel("V (input) [mag]")
    fig.suptitle("Astrometric residuals against magnitude, per scene and epoch", fontsize=10)
    fig.tight_layout()
    png = _save(fig, outdir / "astrometry_by_magnitude.png")
    csv_header = ["variant", "scene", "epoch"]
    for b in PAPER_BINS:
        csv_header += [f"disp_uas_{bin_label(*b)}", f"n_{bin_label(*b)}"]
    csv_header += ["recovered_lt22", "recovered_ge22", "sigma_tt_ave_mas"]
    _write_csv(outdir / "astrometry_by_magnitude.csv", csv_header, csv_rows)
    return (
        "x-position dispersion (measured minus input) after three iterations of 2-sigma "
        "clipping, in microarcsec, stars kept in parentheses (paper tab:simresults); "
        "recovered fractions and the field-averaged tip-tilt kernel (semi-major sigma of the "
        'atmospheric residual over an 11 x 11 grid of the 30" field) as in tab:simparams.\n\n'
        + _md_table(header, rows)
        + f"\n![astrometric residuals]({_rel(png, rundir)})\n"
        + f"\nTable as CSV: [{_rel(outdir / 'astrometry_by_magnitude.csv', rundir)}]"
        f"({_rel(outdir / 'astrometry_by_magnitude.csv', rundir)})\n"
    )


def _sigma_tt(frames_node, rundir: Path) -> float:
    """The paper's sigma_TT,ave [mas] of a frame's scene (NaN when not available).

    Uses the optics module's public tip-tilt model on the scene recorded in the
    frames product (``scene`` attribute), so it describes what was rendered.
    """
    if frames_node is None:
        return math.nan
    try:
        from mavispm.simulate.optics.model import validate_settings
        from mavispm.simulate.optics.tiptilt import TipTiltField, field_average_sigma
    except ImportError:
        return math.nan
    from mavispm.core.products import read_product

    attrs = read_product(
        rundir / frames_node["products"]["main"], "frames", load_arrays=False
    ).attrs
    scene = attrs.get("scene")
    scene = json.loads(scene) if isinstance(scene, str) else scene
    if not isinstance(scene, Mapping):
        return math.nan
    try:
        s = validate_settings(scene.get("optics") or {})
    except MavispmError:  # not the optics model's settings (another renderer)
        return math.nan
    if not s.tiptilt.enabled:
        return 0.0
    return field_average_sigma(TipTiltField(s.tiptilt, s.atmosphere, s.pupil))


def _recovered(frames_node, rundir: Path, measured_mag: np.ndarray) -> list[float]:
    """Fraction of rendered stars recovered, brighter and fainter than m = 22."""
    if frames_node is None:
        return [math.nan, math.nan]
    truth = _read_table(rundir / frames_node["products"]["main"], "frames", "truth")
    tmag = _q(truth, "mag", "mag")
    out = []
    for sel_t, sel_m in ((tmag < 22, measured_mag < 22), (tmag >= 22, measured_mag >= 22)):
        n = int(np.count_nonzero(sel_t))
        out.append(np.count_nonzero(sel_m) / n if n else math.nan)
    return out


def _residual_panel(ax, mag, dx, title):
    ax.plot(mag, dx, ".", ms=2, color="tab:pink", alpha=0.6, label="stars")
    edges = np.arange(
        math.floor(np.nanmin(mag, initial=14)), math.ceil(np.nanmax(mag, initial=27)) + 1
    )
    centres, disps = [], []
    for lo in edges[:-1]:
        sel = (mag >= lo) & (mag < lo + 1)
        disp, kept = clipped_dispersion(dx[sel])
        if kept >= 2:
            centres.append(lo + 0.5)
            disps.append(disp)
    ax.errorbar(
        centres,
        np.zeros(len(centres)),
        yerr=disps,
        fmt="k_",
        capsize=3,
        label="clipped 1-sigma per magnitude",
    )
    lim = 3 * np.nanmax(disps) if disps else 1000.0
    ax.set_ylim(-lim, lim)
    ax.set_ylabel("x measured - input [uas]")
    ax.set_title(title, fontsize=8)
    ax.legend(fontsize=6, loc="upper left")


def pm_accuracy(summary: Mapping, rundir: Path, outdir: Path) -> str:
    """Recipe: proper-motion error against magnitude and radius, per variant.

    Parameters
    ----------
    summary : mapping
        The run's ``summary.json``.
    rundir : pathlib.Path
        The run directory.
    outdir : pathlib.Path
        Where the section's CSV and PNG files go (``report/``).

    Returns
    -------
    str
        The Markdown section.
    """
    import matplotlib.pyplot as plt

    nodes = _nodes(summary, "propermotions")
    if not nodes:
        return "No proper motions in this run.\n"
    bins = (
        (-math.inf, 18.0),
        (18.0, 20.0),
        (20.0, 22.0),
        (22.0, 24.0),
        (24.0, 25.0),
        (25.0, 26.0),
        (26.0, math.inf),
    )
    header = [
        "variant",
        "scene",
        "magnitude",
        "N",
        "RMS dpm_x [uas/yr]",
        "<50 uas/yr",
        "<150 uas/yr",
    ]
    rows, csv_rows = [], []
    fig, axes = plt.subplots(len(nodes), 2, figsize=(9, 2.4 * len(nodes) + 0.6), squeeze=False)
    for (ax_m, ax_r), node in zip(axes, nodes):
        stars = _read_table(rundir / node["products"]["main"], "propermotions", "stars")
        if "pm_x_true" not in stars.colnames:
            continue
        mag = _q(stars, "mag", "mag") if "mag" in stars.colnames else np.full(len(stars), np.nan)
        d = (_q(stars, "pm_x", "mas/yr") - _q(stars, "pm_x_true", "mas/yr")) * 1e3
        radius = _q(stars, "R", "arcsec")
        good = np.isfinite(d)
        if good.any():  # measured PMs are relative to the cluster's mean motion, as on sky
            d = d - np.median(d[good])
        label = _variant_label(node)
        scene = node["labels"].get("scene", "")
        for lo, hi in (*bins, (-math.inf, math.inf)):
            sel = good & (mag >= lo) & (mag < hi) if np.isfinite(lo) or np.isfinite(hi) else good
            n = int(np.count_nonzero(sel))
            if n == 0:
                continue
            rms = float(mad_std(d[sel]))
            f50 = float(np.mean(np.abs(d[sel]) < 50))
            f150 = float(np.mean(np.abs(d[sel]) < 150))
            name = "all" if (math.isinf(lo) and math.isinf(hi)) else bin_label(lo, hi)
            rows.append(
                [label, scene, name, n, f"{rms:.1f}", f"{100 * f50:.0f}%", f"{100 * f150:.0f}%"]
            )
            csv_rows.append([label, scene, name, n, rms, f50, f150])
        xaxes = ((ax_m, mag, "V (input) [mag]"), (ax_r, radius, "R from the centre [arcsec]"))
        for ax, xval, xlabel in xaxes:
            ok50 = good & (np.abs(d) < 50)
            ax.plot(
                xval[good & ~ok50], d[good & ~ok50], ".", ms=2, color="0.5", label=">= 50 uas/yr"
            )
            ax.plot(xval[ok50], d[ok50], ".", ms=2, color="purple", label="< 50 uas/yr")
            ax.set_xlabel(xlabel)
            ax.set_ylabel("pm_x measured - true [uas/yr]")
            ax.set_ylim(-500, 500)
            ax.legend(fontsize=6, loc="upper left", title="|error|", title_fontsize=6)
        ax_m.set_title(panel_title(node, ("study", "point", "scene")), fontsize=8)
        ax_r.set_title(panel_title(node, ("study", "point", "scene")), fontsize=8)
    fig.suptitle(
        "Proper-motion error (x) against magnitude and radius, median offset removed",
        fontsize=10,
    )
    fig.tight_layout()
    png = _save(fig, outdir / "pm_accuracy.png")
    _write_csv(
        outdir / "pm_accuracy.csv",
        ["variant", "scene", "magnitude", "n", "rms_uas_yr", "frac_lt50", "frac_lt150"],
        csv_rows,
    )
    return (
        "Proper-motion error (measured minus true, x component, after removing the median "
        "offset: measured PMs are relative to the cluster's mean motion); robust RMS from "
        "the MAD, and fraction of stars within 50 and 150 microarcsec/yr.\n\n"
        + _md_table(header, rows)
        + f"\n![PM accuracy]({_rel(png, rundir)})\n"
    )


def dispersion_profile(radius: np.ndarray, pm_x: np.ndarray, pm_y: np.ndarray, per_bin: int = 300):
    """1-D PM dispersion in equal-count radial bins.

    Parameters
    ----------
    radius : ndarray
        Projected radius [any unit].
    pm_x, pm_y : ndarray
        Proper-motion components [mas/yr].
    per_bin : int
        Stars per bin (the last bin takes the remainder when it is at least half full).

    Returns
    -------
    (ndarray, ndarray, ndarray)
        Mean radius, dispersion sqrt((var_x + var_y) / 2) and its standard error
        sigma / sqrt(2 (2N - 1)) per bin.
    """
    ok = np.isfinite(radius) & np.isfinite(pm_x) & np.isfinite(pm_y)
    order = np.argsort(radius[ok])
    r, vx, vy = radius[ok][order], pm_x[ok][order], pm_y[ok][order]
    n = r.size
    per_bin = max(2, min(per_bin, n))
    edges = list(range(0, n, per_bin))
    if len(edges) > 1 and n - edges[-1] < per_bin // 2:
        edges.pop()
    edges.append(n)
    rr, ss, ee = [], [], []
    for a, b in zip(edges[:-1], edges[1:]):
        if b - a < 2:
            continue
        s = math.sqrt(0.5 * (vx[a:b].var(ddof=1) + vy[a:b].var(ddof=1)))
        rr.append(r[a:b].mean())
        ss.append(s)
        ee.append(s / math.sqrt(2 * (2 * (b - a) - 1)))
    return np.array(rr), np.array(ss), np.array(ee)


def dispersion_profiles(summary: Mapping, rundir: Path, outdir: Path, per_bin: int = 300) -> str:
    """Recipe: measured and true PM dispersion profiles of every study (fig:imbhresults).

    Parameters
    ----------
    summary : mapping
        The run's ``summary.json``.
    rundir : pathlib.Path
        The run directory.
    outdir : pathlib.Path
        Where the section's CSV and PNG files go (``report/``).
    per_bin : int
        Stars per radial bin.

    Returns
    -------
    str
        The Markdown section.
    """
    import matplotlib.pyplot as plt

    nodes = _nodes(summary, "propermotions")
    if not nodes:
        return "No proper motions in this run.\n"
    fig, ax = plt.subplots(figsize=(6, 4))
    rows = []
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for i, node in enumerate(nodes):
        stars = _read_table(rundir / node["products"]["main"], "propermotions", "stars")
        radius = _q(stars, "R", "arcsec")
        n = len(stars)
        nb = per_bin if n >= 2 * per_bin else max(10, n // 5)
        label = panel_title(node, ("study", "point", "scene"))
        c = colours[i % len(colours)]
        r, s, e = dispersion_profile(
            radius, _q(stars, "pm_x", "mas/yr"), _q(stars, "pm_y", "mas/yr"), nb
        )
        ax.errorbar(r, s, yerr=e, fmt="o", color=c, label=f"{label} measured")
        for j in range(r.size):
            rows.append([label, "measured", f"{r[j]:.2f}", f"{s[j]:.4f}", f"{e[j]:.4f}"])
        if "pm_x_true" in stars.colnames:
            r, s, e = dispersion_profile(
                radius, _q(stars, "pm_x_true", "mas/yr"), _q(stars, "pm_y_true", "mas/yr"), nb
            )
            ax.fill_between(r, s - e, s + e, color=c, alpha=0.25, label=f"{label} truth")
            for j in range(r.size):
                rows.append([label, "truth", f"{r[j]:.2f}", f"{s[j]:.4f}", f"{e[j]:.4f}"])
    ax.set_xlabel("R from the centre [arcsec]")
    ax.set_ylabel("1-D PM dispersion [mas/yr]")
    ax.set_title("Proper-motion dispersion profiles (errors not deconvolved)", fontsize=10)
    ax.legend(fontsize=7)
    fig.tight_layout()
    png = _save(fig, outdir / "dispersion_profiles.png")
    return (
        f"PM dispersion sqrt((var_x + var_y)/2) in equal-count radial bins (up to {per_bin} stars; "
        "measurement errors not deconvolved here; the dynamics stage does that).\n\n"
        + _md_table(["variant", "source", "R [arcsec]", "sigma [mas/yr]", "error [mas/yr]"], rows)
        + f"\n![dispersion profiles]({_rel(png, rundir)})\n"
    )


#: Dynamics results shown first in the model-comparison table (when present).
KEY_DYNAMICS_METRICS = (
    "ln_bayes_factor",
    "ln_bayes_factor_err",
    "ln_bayes_factor_kinematic",
    "ln_b_dark_centre",
    "ln_b_imbh_vs_extended",
    "delta_ln_likelihood",
    "delta_aic",
    "delta_bic",
    "bh_mass_median",
    "bh_mass_lo68",
    "bh_mass_hi68",
    "bh_mass_lo95",
    "bh_mass_hi95",
    "bh_mass_upper95",
    "n_stars",
    "tau_max_imbh",
    "steps_imbh",
)


def _injected_imbh_mass(summary: Mapping, node: Mapping) -> float | None:
    """The ``imbh_mass`` of the cluster catalogue upstream of a dynamics node (None: unknown).

    The cluster node of the same study (id prefix, ``<prefix>dynamics/...`` ->
    ``<prefix>cluster``), else the one cluster node with the same study and point
    labels, else the run's only cluster node.
    """
    clusters = [n for n in summary["nodes"] if n["stage"] == "cluster"]
    prefix = node["id"].split("dynamics/")[0] if "dynamics/" in node["id"] else None
    match = [n for n in clusters if prefix is not None and n["id"] == prefix + "cluster"]
    if not match:
        lab = node.get("labels", {})
        match = [
            n
            for n in clusters
            if all(n.get("labels", {}).get(k, "") == lab.get(k, "") for k in ("study", "point"))
        ]
    if len(match) != 1 and len(clusters) == 1:
        match = clusters
    if len(match) != 1:
        return None
    value = match[0].get("metrics", {}).get("imbh_mass")
    return float(value) if isinstance(value, (int, float)) else None


def model_comparison(summary: Mapping, rundir: Path, outdir: Path) -> str:
    """Recipe: the dynamics stage's model-comparison numbers per study and sweep point.

    One column per fit, one row per result (the key results of
    :data:`KEY_DYNAMICS_METRICS`); every scalar result goes to ``model_comparison.csv``.

    Parameters
    ----------
    summary : mapping
        The run's ``summary.json``.
    rundir : pathlib.Path
        The run directory.
    outdir : pathlib.Path
        Where the section's CSV and PNG files go (``report/``).

    Returns
    -------
    str
        The Markdown section.
    """
    nodes = _nodes(summary, "dynamics")
    if not nodes:
        return "No dynamics fits in this run.\n"
    names: list[str] = []
    for node in nodes:
        names += [k for k in node.get("metrics", {}) if k not in names]
    key = [k for k in KEY_DYNAMICS_METRICS if k in names]
    columns = [
        " ".join(filter(None, (n["labels"].get(k) for k in ("study", "point", "scene")))) or "fit"
        for n in nodes
    ]

    def cell(node, name):
        value = node.get("metrics", {}).get(name)
        return f"{value:.4g}" if isinstance(value, (int, float)) else "-"

    rows = [[name] + [cell(n, name) for n in nodes] for name in key]
    # a simulation's injected IMBH mass (its cluster catalogue's ``imbh_mass``) beside the
    # fitted one, so a biased or unconverged fit cannot pass for the truth
    injected = [_injected_imbh_mass(summary, n) for n in nodes]
    csv_rows = [[name] + [n.get("metrics", {}).get(name, "") for n in nodes] for name in names]
    if any(m is not None for m in injected):
        label = "imbh_mass_injected (truth)"
        at = next((i + 1 for i, r in enumerate(rows) if r[0] == "bh_mass_upper95"), len(rows))
        rows.insert(at, [label] + ["-" if m is None else f"{m:.4g}" for m in injected])
        csv_rows.append([label] + ["" if m is None else m for m in injected])
    csv_path = _write_csv(outdir / "model_comparison.csv", ["result", *columns], csv_rows)
    pngs = [v for n in nodes for k, v in n["products"].items() if k.startswith("plot_")]
    text = _md_table(["result", *columns], rows)
    text += f"\nAll results: [{csv_path.name}]({_rel(csv_path, rundir)})\n"
    text += "".join(f"\n![{Path(p).stem}]({p})\n" for p in pngs)
    return text


def fast_stars(summary: Mapping, rundir: Path, outdir: Path) -> str:
    """Recipe: the fast-star test per study and sweep point (dynamics ``fast_stars`` table).

    One row per dynamics fit: significant fast stars, expected false ones (errors,
    binaries, field), the expected number under the IMBH model, the Poisson
    probability of the observed count without an IMBH, the lower mass limit and
    the Jeans-model ln B; then the significant stars of every fit, and with a
    sweep a plot of the lower limit and the number of fast stars against the first
    swept parameter (one line per value of the others). The dynamics stage's
    ``fast_stars.png`` plots are linked.

    Parameters
    ----------
    summary : mapping
        The run's ``summary.json``.
    rundir : pathlib.Path
        The run directory.
    outdir : pathlib.Path
        Where the section's CSV and PNG files go (``report/``).

    Returns
    -------
    str
        The Markdown section.
    """
    import matplotlib.pyplot as plt

    from mavispm.core.products import read_product

    nodes = _nodes(summary, "dynamics")
    if not nodes:
        return "No dynamics fits in this run.\n"
    header = [
        "fit",
        "stars",
        "fast (significant)",
        "expected false",
        "expected with IMBH",
        "P(N >= n | no IMBH)",
        "M_BH lower limit [Msun]",
        "ln B",
    ]
    rows, star_rows, csv_rows, pngs, sweep_pts = [], [], [], [], []
    for node in nodes:
        label = (
            " ".join(filter(None, (node["labels"].get(k) for k in ("study", "point", "scene"))))
            or "fit"
        )
        prod = read_product(rundir / node["products"]["main"], "dynamics", load_arrays=False)
        a = prod.attrs
        if "fast_stars" not in prod.tables:
            rows.append([label, "-", "not run (set [dynamics.fast_stars])", "", "", "", "", ""])
            continue
        if not a.get("fast_test_possible", False):
            rows.append([label, "-", str(a.get("fast_test_note", "no test")), "", "", "", "", ""])
            continue

        def num(key, a=a):
            v = a.get(key, math.nan)
            return float(getattr(v, "value", v))

        lim = num("bh_mass_lower_limit")
        conf = num("bh_mass_lower_limit_confidence")
        values = [
            int(a["fast_n_stars"]),
            int(a["fast_n_significant"]),
            num("fast_expected_false"),
            num("fast_expected_imbh"),
            num("fast_p_count_ge_no_imbh"),
            lim,
            num("ln_bayes_factor"),
        ]
        rows.append(
            [
                label,
                values[0],
                values[1],
                f"{values[2]:.2g}",
                f"{values[3]:.2g}",
                f"{values[4]:.2g}",
                f"{lim:.0f} ({conf:.0%})" if values[1] else "-",
                f"{values[6]:.1f}",
            ]
        )
        csv_rows.append([label, *values, conf])
        t = prod.tables["fast_stars"]
        for r in t[np.asarray(t["fast"], bool)]:
            star_rows.append(
                [
                    label,
                    int(r["id"]),
                    f"{_q_scalar(r['R'], 'arcsec'):.2f}",
                    f"{_q_scalar(r['v_2d'], 'km/s'):.1f} +- {_q_scalar(r['v_2d_err'], 'km/s'):.1f}",
                    f"{_q_scalar(r['v_esc'], 'km/s'):.1f}",
                    f"{float(r['significance']):.1f}",
                    f"{_q_scalar(r['m_min'], 'solMass'):.0f}",
                ]
            )
        if node.get("sweep"):
            sweep_pts.append((node["sweep"], lim, values[1]))
        png = node["products"].get("plot_fast_stars")
        if png:
            pngs.append((label, png))
    text = (
        "Stars faster than the escape velocity of every mass model without an IMBH "
        "(Häberle et al. 2024); see docs/dynamics.md.\n\n" + _md_table(header, rows)
    )
    csv_path = _write_csv(
        outdir / "fast_stars.csv",
        ["fit", "n_stars", "n_fast", "expected_false", "expected_imbh", "p_count_ge_no_imbh",
         "bh_mass_lower_limit", "ln_bayes_factor", "confidence"],
        csv_rows,
    )  # fmt: skip
    text += f"\nAs CSV: [{csv_path.name}]({_rel(csv_path, rundir)})\n"
    if star_rows:
        text += "\nSignificant fast stars:\n\n" + _md_table(
            ["fit", "id", "R [arcsec]", "v_2D [km/s]", "v_esc [km/s]", "sigma", "M_min [Msun]"],
            star_rows,
        )
    if sweep_pts:
        axes = list(sweep_pts[0][0])
        first = axes[0]
        fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(9, 3.6))
        series: dict[str, list] = {}
        for sw, lim, n in sweep_pts:
            key = ", ".join(f"{k}={sw[k]}" for k in axes[1:]) or "all"
            series.setdefault(key, []).append((_sweep_number(sw.get(first)), lim, n))
        for key, pts in series.items():
            pts.sort()
            ax1.plot([p[0] for p in pts], [p[1] for p in pts], "o-", label=key)
            ax2.plot([p[0] for p in pts], [p[2] for p in pts], "o-", label=key)
        ax1.set_xlabel(first)
        ax1.set_ylabel("M_BH lower limit [Msun]")
        ax1.set_title("Fast-star lower mass limit")
        ax2.set_xlabel(first)
        ax2.set_ylabel("significant fast stars")
        ax2.set_title("Number of fast stars")
        ax1.legend(fontsize=7)
        fig.tight_layout()
        png = _save(fig, outdir / "fast_stars_sweep.png")
        text += f"\n![fast stars against {first}]({_rel(png, rundir)})\n"
    text += "".join(f"\n![fast stars {lab}]({p})\n" for lab, p in pngs)
    return text


def _q_scalar(value, unit: str) -> float:
    return float(value.to_value(unit)) if hasattr(value, "to_value") else float(value)


def _sweep_number(value) -> float:
    if isinstance(value, (list, tuple)) and value:
        nums = [float(v) for v in value if isinstance(v, (int, float))]
        return (max(nums) - min(nums)) if nums else 0.0
    try:
        return float(value)
    except (TypeError, ValueError):
        return 0.0


def colour_shifts(summary: Mapping, rundir: Path, outdir: Path) -> str:
    """Recipe: position and PM errors against colour (see :mod:`.colour_report`).

    Parameters
    ----------
    summary : mapping
        The run's ``summary.json``.
    rundir : pathlib.Path
        The run directory.
    outdir : pathlib.Path
        Where the section's CSV and PNG files go (``report/``).

    Returns
    -------
    str
        The Markdown section.
    """
    from mavispm.workflows.colour_report import colour_shifts as recipe

    return recipe(summary, rundir, outdir)


#: Report recipe name -> function(summary, rundir, outdir) -> Markdown text.
RECIPES: dict[str, Callable[[Mapping, Path, Path], str]] = {
    "astrometry_by_magnitude": astrometry_by_magnitude,
    "pm_accuracy": pm_accuracy,
    "dispersion_profiles": dispersion_profiles,
    "model_comparison": model_comparison,
    "fast_stars": fast_stars,
    "colour_shifts": colour_shifts,
}


RECIPE_TITLES = {
    "astrometry_by_magnitude": "Astrometric accuracy by magnitude",
    "pm_accuracy": "Proper-motion accuracy",
    "dispersion_profiles": "Dispersion profiles",
    "model_comparison": "IMBH model comparison",
    "fast_stars": "Fast stars (stars above the no-IMBH escape velocity)",
    "colour_shifts": "Astrometric and proper-motion errors against colour (refraction)",
}


def _write_csv(path: Path, header: list[str], rows: list[list]) -> Path:
    import csv
    import io

    def fmt(v):
        if isinstance(v, float):
            return "nan" if not math.isfinite(v) else f"{v:.6g}"
        return v

    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(header)
    writer.writerows([fmt(v) for v in r] for r in rows)
    with atomic_path(path) as tmp:
        tmp.write_text(buf.getvalue())
    return path


# --------------------------------------------------------------------------- the report


def stage_report_functions() -> dict[str, str]:
    """The trusted stage-report registry: stage name -> ``"module:function"`` in mavispm.

    ``mavispm report`` calls only these; a run directory names stages, never code.
    """
    from mavispm.workflows.stages import STAGE_MODULES

    return {stage: f"{module}:write_report" for stage, (module, _) in STAGE_MODULES.items()}


def stage_report_names(summary: Mapping, path: str | os.PathLike | None = None) -> list[str]:
    """Stage names whose reports summary.json asks for, checked against the registry.

    ``stage_reports`` is a list of stage names. Run directories written before
    this check hold a mapping of stage name to ``"module:function"``; such an
    entry is accepted only when it names the registered function of that stage.

    Parameters
    ----------
    summary : mapping
        The run's ``summary.json``.
    path : pathlib.Path or str, optional
        The file, named in errors.

    Returns
    -------
    list of str
        The stage names, in the summary's order.

    Raises
    ------
    InputError
        For a name that is not a registered stage report (a run directory is
        data: it can never name code to run).
    """
    raw = summary.get("stage_reports") or []
    trusted = stage_report_functions()
    if isinstance(raw, Mapping):
        for stage, ref in raw.items():
            if trusted.get(stage) != ref:
                raise InputError(
                    f"summary.json: stage_reports entry {stage!r} = {ref!r} is not a registered "
                    f"stage report; run directories hold data, never code (expected stage names "
                    f"{sorted(trusted)})",
                    path=path,
                )
        raw = list(raw)
    if not isinstance(raw, list):
        raise InputError(
            "summary.json: expected stage_reports to be a list of stage names", path=path
        )
    for name in raw:
        if name not in trusted:
            raise InputError(
                f"summary.json: unknown stage report {name!r}; expected one of {sorted(trusted)}",
                path=path,
            )
    return list(raw)


def _fmt_number(value, spec: str) -> str:
    return format(value, spec) if isinstance(value, (int, float)) else "-"


def write_report(rundir: str | os.PathLike, reports: Mapping[str, str] | None = None) -> Path:
    """Write ``report.md`` (and ``report/`` with tables and plots) for a run directory.

    Each selected stage's report function is called on that stage's products;
    stage modules that cannot be imported are skipped.

    Parameters
    ----------
    rundir : path
        A run directory written by :func:`mavispm.workflows.runner.run_workflow`.
    reports : mapping, optional
        Stage name -> ``"module:function"`` of the stage reports, given by the
        calling code (the runner passes its stage registry's). Default: the
        trusted registry :func:`stage_report_functions`. summary.json only
        selects stages by name (``stage_reports``); it never names code.

    Returns
    -------
    pathlib.Path
        The report file.

    Raises
    ------
    InputError
        For a malformed summary.json (see :func:`check_summary`).
    """
    from mavispm.workflows.sweeps import write_sweep_table

    rundir = Path(rundir)
    summary = read_summary(rundir)
    outdir = rundir / "report"
    outdir.mkdir(exist_ok=True)
    parts = [f"# mavispm run: {summary['workflow']}\n"]
    if isinstance(summary.get("description"), str) and summary["description"].strip():
        parts.append(summary["description"].strip() + "\n")
    parts.append(
        f"Workflow file `{summary.get('source', '-')}`, mavispm "
        f"{summary.get('mavispm_version', '-')}, executor {summary.get('executor', '-')}, "
        f"finished {summary.get('created', '-')}, "
        f"wall time {_fmt_number(summary.get('wall_s'), '.1f')} s.\n"
    )
    lost = summary.get("interrupted_tasks")
    if isinstance(lost, list) and lost:
        parts.append(
            f"**{len(lost)} task(s) were redone after an attempt died** (a killed run or a "
            "lost dask worker; products are the same as an uninterrupted run's): "
            + ", ".join(str(x) for x in lost)
            + "\n"
        )
    parts.append("## Stages\n")
    from mavispm.workflows.registry import STAGE_NAMES

    order = sorted(summary["stages"], key=lambda s: (STAGE_NAMES + (s,)).index(s))
    rows = [
        [s, v["tasks"], v["ran"], v["cached"], v.get("failed", 0), f"{v['wall_s']:.2f}"]
        for s, v in ((s, summary["stages"][s]) for s in order)
    ]
    parts.append(_md_table(["stage", "tasks", "ran", "cached", "failed", "compute time [s]"], rows))
    parts.append("\n## Nodes\n")
    rows = []
    for node in summary["nodes"]:
        wall = node.get("wall_s")
        main = node["products"].get("main", "")
        rows.append(
            [
                node["id"],
                node["status"],
                "-" if wall is None else f"{wall:.2f}",
                f"[{Path(main).name}]({main})" if main else "-",
            ]
        )
    parts.append(_md_table(["node", "status", "time [s]", "product"], rows))
    try:
        sweep_files = write_sweep_table(summary, outdir)
    except Exception as exc:  # a malformed sweep must not hide the rest of the report
        sweep_files = []
        parts.append(f"\n*The sweep table could not be produced: {type(exc).__name__}: {exc}*\n")
    if sweep_files:
        parts.append("\n## Sweep\n")
        md = [p for p in sweep_files if p.suffix == ".md"]
        parts.append(md[0].read_text() if md else "")
        parts += [f"\n![{p.stem}]({_rel(p, rundir)})\n" for p in sweep_files if p.suffix == ".png"]
    for recipe in summary.get("outputs", {}).get("tables", []):
        parts.append(f"\n## {RECIPE_TITLES.get(recipe, recipe)}\n")
        parts.append(_safe(RECIPES[recipe], summary, rundir, outdir))
    if reports is None:
        reports = stage_report_functions()
    names = [s for s in stage_report_names(summary, rundir / "summary.json") if s in reports]
    parts += _stage_reports(summary, rundir, outdir, {s: reports[s] for s in names})
    parts.append(warnings_section(summary))
    path = rundir / "report.md"
    with atomic_path(path) as tmp:
        tmp.write_text("\n".join(parts))
    return path


def warnings_section(summary: Mapping) -> str:
    """The warnings the libraries raised while each node ran (from the node records).

    Parameters
    ----------
    summary : mapping
        A run's ``summary.json``.

    Returns
    -------
    str
        A Markdown section: one row per distinct warning with the nodes that raised it,
        or a line saying there were none.
    """
    nodes_of: dict[str, list[str]] = {}
    for node in summary["nodes"]:
        for text in node.get("warnings", []):
            nodes_of.setdefault(text, []).append(node["id"])
    head = "\n## Warnings raised while the nodes ran\n\n"
    if not nodes_of:
        return head + "None.\n"
    rows = []
    for text, ids in nodes_of.items():
        shown = ", ".join(ids[:3]) + (f" and {len(ids) - 3} more" if len(ids) > 3 else "")
        rows.append([text.replace("|", "\\|"), shown])
    return head + _md_table(["warning", "nodes"], rows)


def _safe(func, *args) -> str:
    try:
        return func(*args)
    except Exception as exc:  # a broken report section must not hide the others
        warnings.warn(f"report section {func.__name__} failed: {exc}", stacklevel=2)
        return f"*This section could not be produced: {type(exc).__name__}: {exc}*\n"


def nest_headings(markdown: str, levels: int) -> str:
    r"""Markdown with every ATX heading moved ``levels`` levels down (at most ``######``).

    A stage report is a standalone page with its own ``#`` title; inside the run report it
    sits below ``## <stage> report`` and ``### <group>``, so its headings are demoted to keep
    one ``#`` per document and the levels nested. Lines inside fenced code blocks are left
    as they are.

    Parameters
    ----------
    markdown : str
        The page.
    levels : int
        Levels added to every heading (>= 0).

    Returns
    -------
    str
        The page with demoted headings.

    Examples
    --------
    >>> print(nest_headings("# Title\n\n## Part\n```\n# code\n```", 3))
    #### Title
    <BLANKLINE>
    ##### Part
    ```
    # code
    ```
    """
    out, fence = [], None
    for line in markdown.split("\n"):
        stripped = line.lstrip()
        marker = stripped[:3]
        if marker in ("```", "~~~"):
            fence = None if fence == marker else (fence or marker)
        elif fence is None:
            m = re.match(r"^( {0,3})(#{1,6})(?=\s|$)", line)
            if m:
                depth = min(len(m.group(2)) + levels, 6)
                line = m.group(1) + "#" * depth + line[m.end() :]
        out.append(line)
    return "\n".join(out)


def _stage_reports(
    summary: Mapping, rundir: Path, outdir: Path, reports: Mapping[str, str]
) -> list[str]:
    from mavispm.workflows.registry import resolve

    parts = []
    for stage, ref in reports.items():
        try:
            func = resolve(ref)
        except (ImportError, AttributeError):
            continue
        groups: dict[tuple, list[Path]] = {}
        for node in _nodes(summary, stage):
            lab = node["labels"]
            key = (lab.get("study", ""), lab.get("point", ""), lab.get("scene", ""))
            groups.setdefault(key, []).append(
                contained(rundir, node["products"]["main"], "product", follow_links=False)
            )
        if not groups:
            continue
        parts.append(f"\n## {stage} report\n")
        for key, paths in groups.items():
            name = "_".join(p for p in key if p) or "all"
            target = contained(outdir, Path(stage) / name, "report folder")

            def call(func=func, paths=paths, target=target):
                return list(func(paths, target) or [])

            try:
                files = call()
            except Exception as exc:
                warnings.warn(f"{stage} report for {name} failed: {exc}", stacklevel=2)
                parts.append(f"*{name}: report failed: {type(exc).__name__}: {exc}*\n")
                continue
            parts.append(f"\n### {name}\n")
            for f in map(Path, files):
                rel = _rel(f, rundir)
                if f.suffix == ".png":
                    parts.append(f"![{f.stem}]({rel})\n")
                elif f.suffix == ".md":  # a standalone page: its headings go below ### name
                    parts.append(nest_headings(f.read_text(), 3) + "\n")
                else:
                    parts.append(f"- [{f.name}]({rel})\n")
    return parts
