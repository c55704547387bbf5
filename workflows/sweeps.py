"""Parameter sweeps: axes of values that expand one workflow into many runs.

A sweep axis names a dotted key of the workflow file (``"dynamics.n_walkers"``,
``"studies.imbh.cluster.imbh_mass"``, ``"epochs.times"``, ``"workflow.seed"``)
and a list of values. Several axes combine as a grid (every combination) or,
with ``sweep_mode = "zip"``, element by element. Each combination is a *sweep
point*: a label and a set of overrides applied to the workflow mapping before
it is validated and expanded into stage tasks.

The summary of a swept run is a table with one row per sweep point and study,
the swept values as columns and the stages' scalar metrics (for example ln B of
the IMBH model comparison) as further columns, plus one plot per metric against
the first axis.
"""

from __future__ import annotations

import copy
import itertools
import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mavispm.core.errors import ConfigError

__all__ = [
    "MAX_PLOTS",
    "SweepPoint",
    "apply_point",
    "deep_merge",
    "expand_points",
    "get_dotted",
    "set_dotted",
    "sweep_rows",
    "write_sweep_table",
]


@dataclass(frozen=True)
class SweepPoint:
    """One combination of swept values.

    Parameters
    ----------
    label : str
        File-system safe label (``"imbh_mass=1500,baseline=0-10"``); empty when
        the workflow has no sweep.
    values : dict
        Axis name to value.
    overrides : dict
        Dotted workflow key to value.
    """

    label: str = ""
    values: dict = field(default_factory=dict)
    overrides: dict = field(default_factory=dict)


def deep_merge(base: Mapping, overlay: Mapping) -> dict:
    """Return ``base`` with ``overlay`` merged in (tables merged key by key).

    Neither argument is modified. Non-table values in ``overlay`` replace the
    values of ``base``.

    Parameters
    ----------
    base : mapping
        The settings overlaid.
    overlay : mapping
        The settings that win.

    Returns
    -------
    dict
        A new merged mapping.
    """
    out = copy.deepcopy(dict(base))
    for key, value in overlay.items():
        if isinstance(value, Mapping) and isinstance(out.get(key), Mapping):
            out[key] = deep_merge(out[key], value)
        else:
            out[key] = copy.deepcopy(value)
    return out


def get_dotted(mapping: Mapping, key: str, default: Any = None) -> Any:
    """Value of dotted ``key`` in nested ``mapping`` (``default`` when absent).

    Parameters
    ----------
    mapping : mapping
        Nested tables.
    key : str
        Dotted key, e.g. ``"dynamics.walkers"``.
    default : object
        Returned when a part of the key is missing.

    Returns
    -------
    object
        The value.
    """
    node: Any = mapping
    for part in key.split("."):
        if not isinstance(node, Mapping) or part not in node:
            return default
        node = node[part]
    return node


def set_dotted(mapping: dict, key: str, value: Any, source: str | None = None) -> None:
    """Set dotted ``key`` in nested ``mapping`` in place, creating tables as needed.

    Parameters
    ----------
    mapping : dict
        Nested tables, modified in place.
    key : str
        Dotted key, e.g. ``"dynamics.walkers"``.
    value : object
        The value set.
    source : str, optional
        File named in errors.

    Raises
    ------
    ConfigError
        If a prefix of ``key`` holds a value that is not a table.
    """
    parts = key.split(".")
    node = mapping
    for i, part in enumerate(parts[:-1]):
        nxt = node.setdefault(part, {})
        if not isinstance(nxt, dict):
            raise ConfigError(
                f"cannot sweep '{key}': '{'.'.join(parts[: i + 1])}' is a value, not a table",
                key="sweep.parameter",
                source=source,
            )
        node = nxt
    node[parts[-1]] = copy.deepcopy(value)


def _value_label(value: Any) -> str:
    if isinstance(value, (list, tuple)):
        return "-".join(_value_label(v) for v in value)
    if isinstance(value, float) and math.isfinite(value) and value.is_integer():
        value = int(value)
    return re.sub(r"[^A-Za-z0-9_.+-]+", "_", str(value)).strip("_") or "x"


def expand_points(axes: Sequence[Any], mode: str = "grid") -> list[SweepPoint]:
    """Expand sweep axes into sweep points.

    Parameters
    ----------
    axes : sequence
        Objects with ``name``, ``parameter`` and ``values`` attributes (see
        :class:`mavispm.workflows.config.SweepAxis`).
    mode : {"grid", "zip"}
        ``grid``: every combination; ``zip``: the i-th values of all axes
        together (all axes need the same length).

    Returns
    -------
    list of SweepPoint
        A single empty point when there are no axes.
    """
    if not axes:
        return [SweepPoint()]
    if mode == "zip":
        lengths = {len(a.values) for a in axes}
        if len(lengths) != 1:
            raise ConfigError(
                f"sweep_mode 'zip' needs axes of equal length, got {sorted(lengths)}",
                key="workflow.sweep_mode",
            )
        combos = list(zip(*(a.values for a in axes)))
    else:
        combos = list(itertools.product(*(a.values for a in axes)))
    points = []
    for combo in combos:
        values = {a.name: v for a, v in zip(axes, combo)}
        overrides = {a.parameter: v for a, v in zip(axes, combo)}
        label = ",".join(f"{a.name}={_value_label(v)}" for a, v in zip(axes, combo))
        points.append(SweepPoint(label=label, values=values, overrides=overrides))
    return points


def apply_point(mapping: Mapping, point: SweepPoint, source: str | None = None) -> dict:
    """Return a copy of the workflow ``mapping`` with the point's overrides set.

    Parameters
    ----------
    mapping : mapping
        The workflow's tables.
    point : SweepPoint
        The sweep point (its ``overrides`` map dotted keys to values).
    source : str, optional
        File named in errors.

    Returns
    -------
    dict
        The overridden copy.
    """
    out = copy.deepcopy(dict(mapping))
    for key, value in point.overrides.items():
        set_dotted(out, key, value, source=source)
    return out


def sweep_rows(summary: Mapping) -> list[dict]:
    """Rows of the sweep table from a run summary (one per sweep point and study).

    Each row has ``study``, ``point``, the swept values, and every scalar metric
    of the variant's most downstream stage (the study's result, for example the
    dynamics fit) as ``<stage>[<scene>].<metric>``.

    Parameters
    ----------
    summary : mapping
        The run's ``summary.json``.

    Returns
    -------
    list of dict
        The rows; empty when no node has metrics.
    """
    from mavispm.workflows.registry import STAGE_NAMES

    nodes = [n for n in summary.get("nodes", []) if n.get("metrics")]
    last = max(
        (STAGE_NAMES.index(n["stage"]) for n in nodes if n["stage"] in STAGE_NAMES), default=-1
    )
    rows: dict[tuple[str, str], dict] = {}
    for node in summary.get("nodes", []):
        labels = node.get("labels", {})
        key = (labels.get("study", ""), labels.get("point", ""))
        row = rows.setdefault(key, {"study": key[0], "point": key[1], **node.get("sweep", {})})
        if last >= 0 and node["stage"] != STAGE_NAMES[last]:
            continue
        suffix = "".join(f"[{labels[k]}]" for k in ("scene", "epoch") if labels.get(k))
        for name, value in (node.get("metrics") or {}).items():
            if isinstance(value, (int, float)) and not isinstance(value, bool):
                row[f"{node['stage']}{suffix}.{name}"] = value
    return list(rows.values())


def write_sweep_table(summary: Mapping, outdir: Path) -> list[Path]:
    """Write the sweep table (Markdown and CSV) and one plot per metric.

    Parameters
    ----------
    summary : mapping
        The run's ``summary.json``.
    outdir : pathlib.Path
        The report folder.

    Returns
    -------
    list of pathlib.Path
        The written paths (empty when the run has no sweep).
    """
    from astropy.table import Table

    from mavispm.core.atomic import atomic_path

    axes = summary.get("sweep_axes") or []
    rows = sweep_rows(summary)
    if not axes or not rows:
        return []
    outdir.mkdir(parents=True, exist_ok=True)
    for stale in outdir.glob("sweep_*.png"):  # plots of an earlier report of this run
        stale.unlink()
    columns: list[str] = []
    for row in rows:
        for col in row:
            if col not in columns:
                columns.append(col)
    table = Table(
        rows=[[_cell(row.get(c)) for c in columns] for row in rows],
        names=columns,
        dtype=[object] * len(columns),
    )
    written = []
    md = outdir / "sweep.md"
    with atomic_path(md) as tmp:
        lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
        for row in rows:
            lines.append("| " + " | ".join(_fmt(row.get(c)) for c in columns) + " |")
        tmp.write_text("\n".join(lines) + "\n")
    written.append(md)
    csv = outdir / "sweep.csv"
    with atomic_path(csv) as tmp:
        table.write(tmp, format="ascii.csv", overwrite=True)
    written.append(csv)
    written += _plot_sweep(rows, axes, columns, outdir)
    return written


def _cell(value):
    if isinstance(value, (list, tuple)):
        return _value_label(value)
    return "" if value is None else value


def _fmt(value) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        return f"{value:.4g}"
    if isinstance(value, (list, tuple)):
        return _value_label(value)
    return str(value)


#: At most this many sweep plots (one per result of the most downstream stage).
MAX_PLOTS = 8


def _plot_sweep(rows, axes, columns, outdir: Path) -> list[Path]:
    import matplotlib.pyplot as plt

    from mavispm.core.atomic import atomic_path
    from mavispm.workflows.registry import STAGE_NAMES

    first = axes[0]["name"]
    metrics = [c for c in columns if "." in c and not c.split(".")[-1].startswith("n_")]
    # plot the results of the most downstream stage only (the sweep's science output)
    rank = {s: i for i, s in enumerate(STAGE_NAMES)}
    last = max((rank.get(c.split("[")[0].split(".")[0], -1) for c in metrics), default=-1)
    metrics = [c for c in metrics if rank.get(c.split("[")[0].split(".")[0], -1) == last]
    # a result that is the same at every sweep point (a distance, a reference epoch)
    # says nothing about the sweep: no plot
    metrics = [c for c in metrics if len({repr(row.get(c)) for row in rows}) > 1][:MAX_PLOTS]
    written = []
    for metric in metrics:
        fig, ax = plt.subplots(figsize=(5, 3.5))
        by_series: dict[str, list] = {}
        for row in rows:
            if metric not in row:
                continue
            others = [f"{a['name']}={_fmt(row.get(a['name']))}" for a in axes[1:]]
            series = ", ".join(filter(None, [row["study"], *others])) or metric
            by_series.setdefault(series, []).append((row.get(first), row[metric]))
        for series, pts in by_series.items():
            xs = [_axis_number(p[0]) for p in pts]
            order = sorted(range(len(xs)), key=lambda i: xs[i])
            ax.plot([xs[i] for i in order], [pts[i][1] for i in order], "o-", label=series)
        ax.set_xlabel(first)
        ax.set_ylabel(metric)
        if len(by_series) > 1:
            ax.legend(fontsize=7)
        fig.tight_layout()
        path = outdir / f"sweep_{re.sub(r'[^A-Za-z0-9_.-]+', '_', metric)}.png"
        with atomic_path(path) as tmp:
            fig.savefig(tmp, format="png", dpi=100)
        plt.close(fig)
        written.append(path)
    return written


def _axis_number(value) -> float:
    """A number to place a swept value on a plot axis (a list: its span)."""
    if isinstance(value, (list, tuple)) and value:
        nums = [float(v) for v in value if isinstance(v, (int, float))]
        return (max(nums) - min(nums)) if nums else 0.0
    try:
        return float(value)
    except (TypeError, ValueError):
        return 0.0
