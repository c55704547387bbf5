"""Report recipe ``colour_shifts``: astrometric and proper-motion errors against colour.

Differential atmospheric refraction moves each star's image by an amount that depends
on its spectrum (docs/optics.md): hot stars are lifted towards the zenith more than cool
ones. For every scene rendered with refraction (its frames truth has ``dar_x``), the
recipe bins the stars by effective temperature (the catalogue's ``teff``) and gives,
per bin, the median signed error in x and y:

* per epoch, measured position minus catalogue position (what an observer sees of the
  colour shift in one frame) next to the true DAR shift of the truth table;
* the proper motion minus the true one, next to the motion the DAR change between the
  first and last epoch implies, ``(dar(last) - dar(first)) / T``.

Measured PMs are relative to the cluster's mean motion and each epoch is aligned on the
field, so the measured values are put on the truth's zero point: the median over all
stars of measured minus true is removed from them (a common offset, which an observer
cannot see); a bin's measured minus true value is then its colour-dependent error.
Truth is used for scoring only.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path

import numpy as np

__all__ = ["TEFF_EDGES", "colour_shifts", "teff_bin_label"]

#: Effective-temperature bin edges [K]: M, K, G, F, A and hotter stars.
TEFF_EDGES = (0.0, 4000.0, 5000.0, 6000.0, 7500.0, 10000.0, math.inf)


def teff_bin_label(lo: float, hi: float) -> str:
    """Label of a temperature bin (``<4000 K``, ``4000-5000 K``, ``>=10000 K``).

    Parameters
    ----------
    lo, hi : float
        Bin edges [K] (``lo <= 0``: open below; ``hi`` infinite: open above).

    Returns
    -------
    str
        The label.
    """
    if lo <= 0:
        return f"<{hi:g} K"
    if math.isinf(hi):
        return f">={lo:g} K"
    return f"{lo:g}-{hi:g} K"


def _same_variant(a: Mapping, b: Mapping, scene: bool = True) -> bool:
    keys = ("study", "point", "scene") if scene else ("study", "point")
    return all(a["labels"].get(k, "") == b["labels"].get(k, "") for k in keys)


def _catalogue_teff(summary: Mapping, node: Mapping, rundir: Path) -> dict | None:
    """Star id -> teff [K] from the variant's cluster node (None without one or a teff)."""
    from mavispm.core.catalogue import read_catalogue

    from .report import _nodes, _q

    for cl in _nodes(summary, "cluster"):
        if _same_variant(cl, node, scene=False):
            cat = read_catalogue(rundir / cl["products"]["main"])
            table = next(iter(cat.epochs.values()))
            if "teff" not in table.colnames:
                return None
            return dict(zip(np.asarray(table["id"], np.int64).tolist(), _q(table, "teff", "K")))
    return None


def _binned(teff: np.ndarray, *values: np.ndarray) -> list[list[float]]:
    """Per temperature bin: star count and the median of each value (NaN when empty)."""
    rows = []
    for lo, hi in zip(TEFF_EDGES[:-1], TEFF_EDGES[1:]):
        sel = (teff >= lo) & (teff < hi)
        n = int(np.count_nonzero(sel))
        rows.append([n] + [float(np.median(v[sel])) if n else math.nan for v in values])
    return rows


def _on_truth_zero_point(measured: np.ndarray, true: np.ndarray) -> np.ndarray:
    """``measured`` less the median of ``measured - true`` over all stars (common offset)."""
    d = measured - true
    good = np.isfinite(d)
    return measured - (np.median(d[good]) if good.any() else 0.0)


def colour_shifts(summary: Mapping, rundir: Path, outdir: Path) -> str:
    """Recipe: position and PM errors against effective temperature, refraction scenes.

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

    from .report import (
        BAD_FLAGS,
        _md_table,
        _nodes,
        _q,
        _read_table,
        _rel,
        _save,
        _write_csv,
        panel_title,
    )

    frames = [
        (n, _read_table(rundir / n["products"]["main"], "frames", "truth"))
        for n in _nodes(summary, "frames")
    ]
    frames = [(n, t) for n, t in frames if "dar_x" in t.colnames]
    if not frames:
        return "No scene was rendered with atmospheric refraction.\n"
    labels = [teff_bin_label(lo, hi) for lo, hi in zip(TEFF_EDGES[:-1], TEFF_EDGES[1:])]
    header = ["variant", "scene", "quantity", "axis"] + labels
    rows, csv_rows, panels = [], [], []

    def add(node, quantity, axis, unit, teff, measured, true):
        binned = _binned(teff, _on_truth_zero_point(measured, true), true)
        cells = ["-" if n == 0 else f"{m:+.1f} ({t:+.1f})" for n, m, t in binned]
        lab = node["labels"]
        rows.append([lab.get("study", "") or "-", lab.get("scene", ""), quantity, axis, *cells])
        for (lo, hi), (n, m, t) in zip(zip(TEFF_EDGES[:-1], TEFF_EDGES[1:]), binned):
            csv_rows.append(
                [lab.get("study", ""), lab.get("scene", ""), quantity, axis, unit, lo, hi, n, m, t]
            )

    by_scene: dict[tuple, list] = {}
    for node, truth in frames:
        key = tuple(node["labels"].get(k, "") for k in ("study", "point", "scene"))
        by_scene.setdefault(key, []).append((node, truth))
    for items in by_scene.values():
        node0 = items[0][0]
        teff_of = _catalogue_teff(summary, node0, rundir)
        if teff_of is None:
            continue
        # single epochs: measured x, y minus the catalogue position, against the true DAR
        for fnode, truth in items:
            snode = next(
                (n for n in _nodes(summary, "stars") if n["id"] == fnode["id"].replace(
                    "frames/", "stars/", 1
                )),
                None,
            )  # fmt: skip
            if snode is None:
                continue
            stars = _read_table(rundir / snode["products"]["main"], "measured", "stars")
            ok = (np.asarray(stars["flag"]).astype(int) & BAD_FLAGS) == 0
            t_ids = np.asarray(truth["id"], np.int64)
            index = {int(i): k for k, i in enumerate(t_ids)}
            ids = np.asarray(stars["id"], np.int64)
            rows_t = np.array([index.get(int(i), -1) for i in ids])
            ok &= rows_t >= 0
            teff = np.array([teff_of.get(int(i), np.nan) for i in ids])
            ok &= np.isfinite(teff)
            r = rows_t[ok]
            epoch = fnode["labels"].get("epoch", "")
            for axis in ("x", "y"):
                meas = (_q(stars, axis, "arcsec")[ok] - _q(truth, f"{axis}_cat", "arcsec")[r]) * 1e6
                dar = _q(truth, f"dar_{axis}", "arcsec")[r] * 1e6
                add(fnode, f"position {epoch} [uas]", axis, "uas", teff[ok], meas, dar)
        # proper motions against the DAR change between the first and last epoch
        pm_node = next(
            (n for n in _nodes(summary, "propermotions") if _same_variant(n, node0)), None
        )
        if pm_node is None or len(items) < 2:
            continue
        pms = _read_table(rundir / pm_node["products"]["main"], "propermotions", "stars")
        if "pm_x_true" not in pms.colnames:
            continue
        epochs = []
        for fnode, truth in items:
            attrs = _read_attrs(rundir / fnode["products"]["main"])
            epochs.append((float(attrs["epoch"].to_value("yr")), truth))
        epochs.sort(key=lambda e: e[0])
        (t0, first), (t1, last) = epochs[0], epochs[-1]
        ids = np.asarray(pms["id"], np.int64)
        i0 = {int(i): k for k, i in enumerate(np.asarray(first["id"], np.int64))}
        i1 = {int(i): k for k, i in enumerate(np.asarray(last["id"], np.int64))}
        keep = np.array([int(i) in i0 and int(i) in i1 and int(i) in teff_of for i in ids])
        for name in ("pm_x", "pm_y", "pm_x_true", "pm_y_true"):
            keep &= np.isfinite(_q(pms, name, "mas/yr"))
        sel = ids[keep]
        teff = np.array([teff_of[int(i)] for i in sel])
        a = np.array([i0[int(i)] for i in sel], dtype=np.int64)
        b = np.array([i1[int(i)] for i in sel], dtype=np.int64)
        span = t1 - t0
        for axis in ("x", "y"):
            meas = (_q(pms, f"pm_{axis}", "mas/yr") - _q(pms, f"pm_{axis}_true", "mas/yr"))[keep]
            meas = meas * 1e3
            true = (
                (_q(last, f"dar_{axis}", "arcsec")[b] - _q(first, f"dar_{axis}", "arcsec")[a])
                * 1e6
                / span
            )
            add(pm_node, "PM [uas/yr]", axis, "uas/yr", teff, meas, true)
            if axis == "x":
                panels.append((pm_node, teff, _on_truth_zero_point(meas, true), true))
    if not rows:
        return (
            "Scenes with refraction found, but no measured stars with a catalogue `teff` "
            "to bin them by.\n"
        )
    _write_csv(
        outdir / "colour_shifts.csv",
        ["study", "scene", "quantity", "axis", "unit", "teff_lo", "teff_hi", "n", "median", "true"],
        csv_rows,
    )
    text = (
        "Median signed shift per effective-temperature bin, measured (true): a position is "
        "the measured minus the catalogue position, its truth the DAR shift of the frame; a "
        "PM is the measured minus the true motion, its truth the DAR change between the "
        "first and last epoch over the baseline. Measured values are put on the truth's zero "
        "point (the median of measured minus true over all stars removed: epochs are aligned "
        "and PMs relative), so measured minus true in a bin is its colour-dependent error. "
        "Scenes rendered with refraction only.\n\n" + _md_table(header, rows)
    )
    if panels:
        fig, axes = plt.subplots(
            len(panels), 1, figsize=(7, 2.6 * len(panels) + 0.5), squeeze=False
        )
        for ax, (node, teff, meas, true) in zip(axes[:, 0], panels):
            ax.semilogx(teff, meas, ".", ms=2, color="0.6", label="stars (measured)")
            centres, med, tru = [], [], []
            for n, m, t, lo, hi in (
                (*row, lo, hi)
                for row, lo, hi in zip(_binned(teff, meas, true), TEFF_EDGES[:-1], TEFF_EDGES[1:])
            ):
                if n:
                    sel = (teff >= lo) & (teff < hi)
                    centres.append(float(np.median(teff[sel])))
                    med.append(m)
                    tru.append(t)
            ax.plot(centres, med, "o-", color="purple", label="median, measured")
            ax.plot(centres, tru, "k--", label="median, true DAR change")
            lim = 3 * np.nanmax(np.abs(np.r_[med, tru])) if med else 10.0
            ax.set_ylim(-lim - 5, lim + 5)
            ax.set_ylabel("pm_x - true [uas/yr]")
            ax.set_title(panel_title(node, ("study", "point", "scene")), fontsize=8)
            ax.legend(fontsize=6)
        axes[-1, 0].set_xlabel("effective temperature [K]")
        fig.suptitle("Proper-motion error against colour (truth's zero point)", fontsize=10)
        fig.tight_layout()
        png = _save(fig, outdir / "colour_shifts.png")
        text += f"\n![PM error against colour]({_rel(png, rundir)})\n"
    return text


def _read_attrs(path: Path) -> dict:
    from mavispm.core.products import read_product

    return read_product(path, "frames", load_arrays=False).attrs
