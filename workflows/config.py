"""Workflow files (TOML): schema, validation and expansion into variants.

A workflow file describes a whole study. Its top-level tables are:

``[workflow]``
    ``name``, ``description``, ``seed`` (int), ``sweep_mode`` ("grid" or "zip"),
    ``executor`` ("threads", "processes", "serial"), ``workers`` (0 = all CPUs).
``[cluster]``
    Settings of the cluster generator stage (``mavispm simulate cluster``), *or*
``[catalogue]``
    ``path`` of an existing catalogue product (relative to the workflow file).
``[epochs]``
    ``times`` (years; numbers or strings such as ``"10 yr"``), optional ``names``.
``[scene]`` (with ``[scene.optics]``), ``[measure]``
    Base settings of the rendered scene (``mavispm simulate frames``; its
    ``optics`` sub-table is the optics model, whose PSF grid is built once per
    distinct optics as its own node) and of the star measurement.
    ``[scenes.NAME]`` tables overlay ``[scene]`` per scene
    (``[scenes.III.optics.tiptilt]``); ``[scenes.NAME.measure]`` overlays ``[measure]``.
    A ``calibration`` table in a scene (``[scenes.NAME.calibration]``, keys of
    ``mavispm simulate calibration``'s mask) adds a calibration node imaging the mask
    through the scene's distortion; the scene's frames then carry the post-calibration
    residual distortion.
``[propermotions]``, ``[dynamics]``
    Stage settings; present means "run this stage".
``[outputs]``
    ``fits``, ``plots``, ``report`` (bools), ``link`` ("hardlink", "copy",
    "symlink": how products appear in the run directory), ``tables`` (report
    recipes, see :data:`mavispm.workflows.report.RECIPES`).
``[studies.NAME]``
    Overlays of the sections above (for example the IMBH and no-IMBH cluster).
``[[sweep]]``
    Axes: ``parameter`` (dotted key), ``values`` (list), optional ``name``.

Everything is checked when the file is loaded, before any work starts: unknown
keys, wrong types and units, missing files and impossible combinations raise
:class:`~mavispm.core.errors.ConfigError` naming the file, the key and what
was expected. Stage tables are checked by each stage's ``validate_settings``
for every study and sweep point.
"""

from __future__ import annotations

import json
import os
import re
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import astropy.units as u

from mavispm.core.config import check_known_keys, from_mapping
from mavispm.core.errors import ConfigError, InputError
from mavispm.core.paths import check_name
from mavispm.workflows.registry import StageRegistry
from mavispm.workflows.sweeps import SweepPoint, apply_point, deep_merge, expand_points

__all__ = [
    "Epoch",
    "OutputsSection",
    "RESERVED_NAMES",
    "SECTION_STAGE",
    "SHIPPED_DIR",
    "STUDY_SECTIONS",
    "SceneConfig",
    "SweepAxis",
    "Variant",
    "Workflow",
    "WorkflowSection",
    "load_workflow",
    "parse_workflow",
    "read_toml",
    "resolve_workflow_path",
    "shipped_workflows",
]

#: Folder of the workflow files shipped with mavispm.
SHIPPED_DIR = Path(__file__).resolve().parent

#: Stage sections a study may overlay.
STUDY_SECTIONS = (
    "cluster",
    "catalogue",
    "epochs",
    "scene",
    "scenes",
    "measure",
    "propermotions",
    "dynamics",
)
TOP_SECTIONS = ("workflow", "outputs", "studies", "sweep", *STUDY_SECTIONS)

#: Names a workflow may not take: folders of the work directory that are not run directories.
RESERVED_NAMES = ("store", "products", "report")

#: Workflow section -> registry stage name that validates it.
SECTION_STAGE = {
    "cluster": "cluster",
    "optics": "optics",
    "calibration": "calibration",
    "scene": "frames",
    "measure": "stars",
    "propermotions": "propermotions",
    "dynamics": "dynamics",
}


@dataclass(frozen=True)
class WorkflowSection:
    """The ``[workflow]`` table.

    Parameters
    ----------
    name : str
        Workflow name (run directory and report title).
    description : str
        Free text for the report.
    seed : int
        Base seed (>= 0); every node's seed is derived from it and the node's path.
    sweep_mode : {"grid", "zip"}
        How ``[[sweep]]`` axes combine: every combination, or element-wise.
    executor : {"threads", "processes", "serial"}
        Local executor (overridden by ``--scheduler``).
    workers : int
        Local pool size; 0 means all CPUs.
    """

    name: str = ""
    description: str = ""
    seed: int = 1
    sweep_mode: Literal["grid", "zip"] = "grid"
    executor: Literal["threads", "processes", "serial"] = "threads"
    workers: int = 0

    def __post_init__(self):
        if self.workers < 0:
            raise ValueError(f"workers must be >= 0 (0 = all CPUs), got {self.workers}")
        if self.seed < 0:
            raise ValueError(f"seed must be a non-negative integer, got {self.seed}")


@dataclass(frozen=True)
class OutputsSection:
    """The ``[outputs]`` table.

    Parameters
    ----------
    fits : bool
        Also write FITS images of the frames.
    plots : bool
        Write the stage plots.
    report : bool
        Write ``report.md`` after the run.
    link : {"hardlink", "copy", "symlink"}
        How products appear in the run directory.
    tables : tuple of str
        Report recipes to run (docs/workflows.md, "Report recipes").
    """

    fits: bool = True
    plots: bool = True
    report: bool = True
    link: Literal["hardlink", "copy", "symlink"] = "hardlink"
    tables: tuple[str, ...] = ()


@dataclass(frozen=True)
class SweepAxis:
    """One ``[[sweep]]`` axis.

    Parameters
    ----------
    parameter : str
        Dotted workflow key swept, e.g. ``"dynamics.walkers"``.
    values : tuple
        The values it takes.
    name : str
        Axis name in tables and node paths (default: the key's last part).
    """

    parameter: str = ""
    values: tuple[Any, ...] = ()
    name: str = ""


@dataclass(frozen=True)
class SceneConfig:
    """Effective settings of one scene: render scene (optics included), optics, measurement.

    Parameters
    ----------
    name : str
        Scene name (empty for the single ``[scene]``).
    scene : dict
        The render settings (``[scene]`` with the scene's overlay).
    optics : dict or None
        The optics settings of the scene.
    measure : dict or None
        The measurement settings of the scene.
    """

    name: str
    scene: dict
    optics: dict | None
    measure: dict | None
    calibration: dict | None = None


@dataclass(frozen=True)
class Epoch:
    """An observing epoch: catalogue table name and time [yr].

    Parameters
    ----------
    name : str
        Epoch (catalogue table) name.
    time : float
        Epoch time [yr].
    """

    name: str
    time: float


@dataclass(frozen=True)
class Variant:
    """One fully resolved run of the workflow: a study at a sweep point.

    Parameters
    ----------
    study : str
        Study name ("" when the file has no ``[studies]``).
    point : SweepPoint
    seed : int
        The workflow seed of this variant.
    cluster : dict or None
        Cluster stage settings (None when an external catalogue is used).
    catalogue : pathlib.Path or None
        External catalogue product.
    epochs : tuple of Epoch
    scenes : tuple of SceneConfig
    propermotions, dynamics : dict or None
    mapping : dict
        The effective workflow mapping (for provenance).
    """

    study: str
    point: SweepPoint
    seed: int
    cluster: dict | None
    catalogue: Path | None
    epochs: tuple[Epoch, ...]
    scenes: tuple[SceneConfig, ...]
    propermotions: dict | None
    dynamics: dict | None
    mapping: dict = field(repr=False, default_factory=dict)

    @property
    def label(self) -> str:
        """``study/point`` path label (empty parts dropped)."""
        return "/".join(p for p in (self.study, self.point.label) if p)


@dataclass(frozen=True)
class Workflow:
    """A loaded, validated workflow file.

    Parameters
    ----------
    source : pathlib.Path
        The workflow file.
    name : str
        Run name (``[workflow] name`` or the file's stem).
    meta : WorkflowSection
    outputs : OutputsSection
    axes : tuple of SweepAxis
    variants : tuple of Variant
    mapping : dict
        The file as read.
    """

    source: Path
    name: str
    meta: WorkflowSection
    outputs: OutputsSection
    axes: tuple[SweepAxis, ...]
    variants: tuple[Variant, ...]
    mapping: dict = field(repr=False, default_factory=dict)


def shipped_workflows() -> list[str]:
    """Names of the workflow files shipped with mavispm."""
    return sorted(p.name for p in SHIPPED_DIR.glob("*.toml"))


def resolve_workflow_path(name: str | os.PathLike) -> Path:
    """Find a workflow file: an existing path, else a shipped workflow of that name.

    ``"quickstart"``, ``"quickstart.toml"`` and ``"workflows/quickstart.toml"``
    all find the shipped quickstart when no such file exists here.

    Parameters
    ----------
    name : str or os.PathLike
        A path, or the name of a shipped workflow.

    Returns
    -------
    pathlib.Path
        The workflow file.

    Raises
    ------
    ConfigError
        When neither exists; the message lists the shipped workflows.
    """
    path = Path(name)
    if path.is_file():
        return path
    for candidate in (SHIPPED_DIR / path.name, SHIPPED_DIR / f"{path.name}.toml"):
        if candidate.is_file():
            return candidate
    raise ConfigError(
        f"workflow file not found; expected an existing TOML file or one of the "
        f"shipped workflows {shipped_workflows()}",
        source=str(name),
    )


def read_toml(path: Path) -> dict:
    """Parse a TOML file, turning syntax errors into :class:`ConfigError`.

    Parameters
    ----------
    path : pathlib.Path
        The TOML file.

    Returns
    -------
    dict
        Its tables.

    Raises
    ------
    ConfigError
        Naming the file when it cannot be read or is not valid TOML.
    """
    try:
        with open(path, "rb") as fh:
            return tomllib.load(fh)
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ConfigError(f"invalid TOML: {exc}", source=str(path)) from None
    except OSError as exc:
        raise ConfigError(f"cannot read workflow file ({exc.strerror})", source=str(path)) from None


def load_workflow(
    path: str | os.PathLike,
    registry: StageRegistry | None = None,
    overrides: Mapping[str, Any] | None = None,
) -> Workflow:
    """Read and validate a workflow file.

    Parameters
    ----------
    path : str or os.PathLike
        A TOML file, or the name of a shipped workflow.
    registry : StageRegistry, optional
        Stage functions used to validate stage tables (default: the real stages).
    overrides : mapping, optional
        Dotted key to value, applied on top of the file (tests, command line).

    Returns
    -------
    Workflow

    Raises
    ------
    ConfigError
        For any problem in the file, before any work starts.
    """
    if registry is None:
        from mavispm.workflows.stages import default_registry

        registry = default_registry()
    source = resolve_workflow_path(path).resolve()
    mapping = read_toml(source)
    if overrides:
        mapping = apply_point(mapping, SweepPoint(overrides=dict(overrides)), source=source)
    return parse_workflow(mapping, source, registry)


def parse_workflow(mapping: Mapping, source: Path, registry: StageRegistry) -> Workflow:
    """Validate a workflow mapping read from ``source`` (see :func:`load_workflow`).

    Parameters
    ----------
    mapping : mapping
        The workflow's tables as read from TOML.
    source : pathlib.Path
        The file it came from (named in errors, base of relative paths).
    registry : StageRegistry
        The stages whose settings validators check the stage tables.

    Returns
    -------
    Workflow
        The validated workflow with its resolved variants.

    Raises
    ------
    ConfigError
        Naming the file and key of the first bad setting.
    """
    src = str(source)
    check_known_keys(mapping, TOP_SECTIONS, "", src)
    for key in TOP_SECTIONS:
        if key in mapping and key != "sweep" and not isinstance(mapping[key], Mapping):
            raise ConfigError(
                f"expected a table ([{key}]), got {mapping[key]!r}", key=key, source=src
            )
    meta = from_mapping(WorkflowSection, mapping.get("workflow"), prefix="workflow", source=src)
    outputs = from_mapping(OutputsSection, mapping.get("outputs"), prefix="outputs", source=src)
    _check_recipes(outputs, src)
    axes = _parse_axes(mapping.get("sweep", []), src)
    studies = mapping.get("studies", {}) or {}
    for sname, overlay in studies.items():
        if not isinstance(overlay, Mapping):
            raise ConfigError(
                f"expected a table of section overlays, got {overlay!r}",
                key=f"studies.{sname}",
                source=src,
            )
        check_known_keys(overlay, STUDY_SECTIONS, f"studies.{sname}", src)
        check_name(sname, f"studies.{sname}", src, what="study name")
    points = expand_points(axes, meta.sweep_mode)
    validated: dict[str, Any] = {}
    variants = []
    for point in points:
        swept = apply_point(mapping, point, source=src)
        for sname in list((swept.get("studies") or {}) or [""]):
            variants.append(_variant(swept, sname, point, source, registry, validated))
    default = re.sub(r"[^A-Za-z0-9_.+=,-]+", "_", source.stem).lstrip(".-") or "workflow"
    name = check_name(meta.name or default, "workflow.name", src, RESERVED_NAMES, "workflow name")
    return Workflow(
        source=source,
        name=name,
        meta=meta,
        outputs=outputs,
        axes=tuple(axes),
        variants=tuple(variants),
        mapping=dict(mapping),
    )


def _check_recipes(outputs: OutputsSection, src: str) -> None:
    from mavispm.workflows.report import RECIPES

    for i, recipe in enumerate(outputs.tables):
        if recipe not in RECIPES:
            raise ConfigError(
                f"unknown report table {recipe!r}; expected one of {sorted(RECIPES)}",
                key=f"outputs.tables[{i}]",
                source=src,
            )


def _parse_axes(raw, src: str) -> list[SweepAxis]:
    if isinstance(raw, Mapping):
        raw = [raw]
    if not isinstance(raw, list):
        raise ConfigError("expected [[sweep]] tables", key="sweep", source=src)
    axes = []
    names = set()
    for i, item in enumerate(raw):
        axis = from_mapping(SweepAxis, item, prefix=f"sweep[{i}]", source=src)
        if not axis.parameter:
            raise ConfigError(
                "expected a dotted workflow key such as 'dynamics.n_walkers'",
                key=f"sweep[{i}].parameter",
                source=src,
            )
        top = axis.parameter.split(".")[0]
        if top not in TOP_SECTIONS or top in ("sweep", "outputs"):
            raise ConfigError(
                f"cannot sweep '{axis.parameter}': its first part must be one of "
                f"{[s for s in TOP_SECTIONS if s not in ('sweep', 'outputs')]}",
                key=f"sweep[{i}].parameter",
                source=src,
            )
        if axis.parameter in ("workflow.name", "workflow.executor", "workflow.workers"):
            raise ConfigError(
                "only 'workflow.seed' of the [workflow] table can be swept",
                key=f"sweep[{i}].parameter",
                source=src,
            )
        if not axis.values:
            raise ConfigError(
                "expected a non-empty list of values", key=f"sweep[{i}].values", source=src
            )
        name = check_name(
            axis.name or axis.parameter.split(".")[-1], f"sweep[{i}].name", src, what="axis name"
        )
        if name in names:
            raise ConfigError(
                f"two sweep axes are named '{name}'; give them distinct 'name's",
                key=f"sweep[{i}].name",
                source=src,
            )
        names.add(name)
        axes.append(SweepAxis(parameter=axis.parameter, values=tuple(axis.values), name=name))
    return axes


def _variant(
    mapping: Mapping,
    study: str,
    point: SweepPoint,
    source: Path,
    registry: StageRegistry,
    validated: dict,
) -> Variant:
    src = str(source)
    where = " ".join(
        p
        for p in (
            f"study '{study}'" if study else "",
            f"sweep point {point.label}" if point.label else "",
        )
        if p
    )
    base = {k: v for k, v in mapping.items() if k in STUDY_SECTIONS}
    eff = deep_merge(base, (mapping.get("studies") or {}).get(study, {})) if study else base
    meta = from_mapping(WorkflowSection, mapping.get("workflow"), prefix="workflow", source=src)
    ctx = _Context(src, where, registry, validated)

    for key in STUDY_SECTIONS:
        if key in eff and not isinstance(eff[key], Mapping):
            raise ConfigError(
                f"expected a table, got {eff[key]!r}{ctx.suffix}", key=key, source=src
            )
    if "cluster" in eff and "catalogue" in eff:
        raise ConfigError(
            "give either [cluster] (generate a catalogue) or [catalogue] (use an existing "
            f"file), not both{ctx.suffix}",
            key="catalogue",
            source=src,
        )
    if "cluster" not in eff and "catalogue" not in eff:
        raise ConfigError(
            f"no cluster source: add a [cluster] table or a [catalogue] path{ctx.suffix}",
            key="cluster",
            source=src,
        )
    catalogue = None
    cluster = None
    if "catalogue" in eff:
        catalogue, file_epochs = _external_catalogue(eff["catalogue"], source, ctx)
        epochs = _epochs(eff.get("epochs"), ctx, available=file_epochs)
    else:
        cluster = _cluster_settings(eff["cluster"], source, ctx)
        ctx.validate("cluster", cluster, "cluster")
        epochs = _epochs(eff.get("epochs"), ctx, available=None)

    scenes = _scenes(eff, ctx)
    pm = eff.get("propermotions")
    dyn = eff.get("dynamics")
    if pm is not None:
        if not scenes or any(s.measure is None for s in scenes):
            raise ConfigError(
                f"[propermotions] needs measured stars: add a [scene] and a [measure] table{ctx.suffix}",
                key="propermotions",
                source=src,
            )
        if len(epochs) < 2:
            raise ConfigError(
                f"[propermotions] needs at least 2 epochs, got {len(epochs)}{ctx.suffix}",
                key="epochs.times",
                source=src,
            )
        ctx.validate("propermotions", pm, "propermotions")
    if dyn is not None:
        if pm is None:
            raise ConfigError(
                f"[dynamics] needs proper motions: add a [propermotions] table{ctx.suffix}",
                key="dynamics",
                source=src,
            )
        ctx.validate("dynamics", dyn, "dynamics")
    return Variant(
        study=study,
        point=point,
        seed=meta.seed,
        cluster=cluster,
        catalogue=catalogue,
        epochs=tuple(epochs),
        scenes=tuple(scenes),
        propermotions=None if pm is None else dict(pm),
        dynamics=None if dyn is None else dict(dyn),
        mapping=eff,
    )


@dataclass
class _Context:
    src: str
    where: str
    registry: StageRegistry
    validated: dict

    @property
    def suffix(self) -> str:
        return f" (in {self.where})" if self.where else ""

    def validate(self, section: str, settings: Mapping, key: str) -> None:
        """Validate a stage table once per distinct content."""
        stage = SECTION_STAGE[section]
        if stage not in self.registry:
            raise ConfigError(
                f"stage '{stage}' is not available in this installation", key=key, source=self.src
            )
        memo = (stage, json.dumps(settings, sort_keys=True, default=str))
        if memo in self.validated:
            return
        try:
            self.validated[memo] = self.registry.validate(stage, settings, source=self.src)
        except ConfigError as exc:
            msg = str(exc)
            if exc.source is None:
                msg = f"file '{self.src}': {msg}"
            err = ConfigError(f"{msg} (table [{key}]{', ' + self.where if self.where else ''})")
            err.key, err.source = exc.key or key, self.src
            raise err from None
        except ImportError as exc:
            raise ConfigError(
                f"stage '{stage}' cannot be loaded ({exc}); is this mavispm build complete?",
                key=key,
                source=self.src,
            ) from None
        except (InputError, ValueError, TypeError) as exc:
            raise ConfigError(
                f"invalid settings: {exc}{self.suffix}", key=key, source=self.src
            ) from None


def _cluster_settings(table: Mapping, source: Path, ctx: _Context) -> dict:
    """The [cluster] table with workflow-owned keys checked and file paths made absolute."""
    if "epochs" in table:
        raise ConfigError(
            "set the epochs in the [epochs] table (times = [...]), not in [cluster]",
            key="cluster.epochs",
            source=ctx.src,
        )
    cluster = dict(table)
    external = cluster.get("external")
    if isinstance(external, Mapping) and isinstance(external.get("path"), str):
        path = _existing_file(
            external["path"], source, "cluster.external.path", "external star list", ctx
        )
        cluster["external"] = {**external, "path": str(path)}
    return cluster


def _existing_file(raw: str, source: Path, key: str, what: str, ctx: _Context) -> Path:
    """``raw`` as an absolute path (relative to the workflow file), which must exist."""
    path = Path(raw).expanduser()
    if not path.is_absolute():
        path = (source.parent / path).resolve()
    if not path.is_file():
        raise ConfigError(f"{what} '{path}' does not exist{ctx.suffix}", key=key, source=ctx.src)
    return path


def _external_catalogue(table: Mapping, source: Path, ctx: _Context):
    check_known_keys(table, ("path",), "catalogue", ctx.src)
    raw = table.get("path")
    if not isinstance(raw, str) or not raw:
        raise ConfigError(
            f"expected the path of a catalogue product (HDF5){ctx.suffix}",
            key="catalogue.path",
            source=ctx.src,
        )
    path = _existing_file(raw, source, "catalogue.path", "catalogue file", ctx)
    from mavispm.core.catalogue import read_catalogue

    try:
        cat = read_catalogue(path)
    except InputError as exc:
        raise ConfigError(
            f"not a usable catalogue: {exc}", key="catalogue.path", source=ctx.src
        ) from None
    times = {n: float(t.to_value(u.yr)) for n, t in cat.epoch_times().items()}
    return path, times


def _epochs(table: Mapping | None, ctx: _Context, available: dict | None) -> list[Epoch]:
    src = ctx.src
    if table is None:
        if available is not None:
            return [Epoch(n, t) for n, t in available.items()]
        return [Epoch("e0", 0.0)]
    check_known_keys(table, ("times", "names"), "epochs", src)
    raw = table.get("times")
    if raw is None and available is not None:
        raw = list(available.values())
    if not isinstance(raw, list) or not raw:
        raise ConfigError(
            f"expected a non-empty list of epoch times in years, e.g. [0, 10]{ctx.suffix}",
            key="epochs.times",
            source=src,
        )
    times = []
    for i, value in enumerate(raw):
        try:
            if isinstance(value, bool):
                raise TypeError
            q = u.Quantity(value)
            times.append(float(q.to_value(u.yr) if q.unit != u.one else q.value))
        except (TypeError, ValueError, u.UnitsError):
            raise ConfigError(
                f"expected a time in years (number or string like '10 yr'), got {value!r}{ctx.suffix}",
                key=f"epochs.times[{i}]",
                source=src,
            ) from None
    if len(set(times)) != len(times):
        raise ConfigError(
            f"duplicate epoch times {times}{ctx.suffix}", key="epochs.times", source=src
        )
    names = table.get("names")
    if names is None:
        if available is not None:
            by_time = {t: n for n, t in available.items()}
            names = []
            for t in times:
                match = [n for tt, n in by_time.items() if abs(tt - t) < 1e-9]
                if not match:
                    raise ConfigError(
                        f"the catalogue has no epoch at {t} yr; it has {sorted(available.values())}"
                        f"{ctx.suffix}",
                        key="epochs.times",
                        source=src,
                    )
                names.append(match[0])
        else:  # generated catalogues name their epochs e0, e1, ... in time order
            times = sorted(times)
            names = [f"e{i}" for i in range(len(times))]
    if (
        not isinstance(names, list)
        or len(names) != len(times)
        or not all(isinstance(n, str) and n for n in names)
        or len(set(names)) != len(names)
    ):
        raise ConfigError(
            f"expected {len(times)} distinct epoch names (strings), got {names!r}{ctx.suffix}",
            key="epochs.names",
            source=src,
        )
    for i, n in enumerate(names):
        check_name(n, f"epochs.names[{i}]", src, what="epoch name")
    if available is not None:
        for n, t in zip(names, times):
            if n not in available or abs(available[n] - t) > 1e-9:
                raise ConfigError(
                    f"epoch '{n}' at {t} yr is not in the catalogue (it has {available}){ctx.suffix}",
                    key="epochs",
                    source=src,
                )
    epochs = sorted((Epoch(n, t) for n, t in zip(names, times)), key=lambda e: e.time)
    return epochs


def _scenes(eff: Mapping, ctx: _Context) -> list[SceneConfig]:
    src = ctx.src
    base_scene = eff.get("scene")
    base_measure = eff.get("measure")
    overlays = eff.get("scenes") or {}
    if not overlays and base_scene is None:
        if base_measure is not None:
            raise ConfigError(
                f"[measure] needs rendered frames: add a [scene] table{ctx.suffix}",
                key="scene",
                source=src,
            )
        return []
    out = []
    for name, overlay in (overlays or {"main": {}}).items():
        prefix = f"scenes.{name}"
        check_name(name, prefix, src, what="scene name")
        if not isinstance(overlay, Mapping):
            raise ConfigError(f"expected a table, got {overlay!r}", key=prefix, source=src)
        overlay = dict(overlay)
        measure_overlay = overlay.pop("measure", None)
        if measure_overlay is not None and not isinstance(measure_overlay, Mapping):
            raise ConfigError(
                f"expected a table, got {measure_overlay!r}", key=f"{prefix}.measure", source=src
            )
        if "optics" in overlay and not isinstance(overlay["optics"], Mapping):
            raise ConfigError(
                f"expected a table, got {overlay['optics']!r}", key=f"{prefix}.optics", source=src
            )
        label = prefix if overlays else "scene"
        scene = deep_merge(base_scene or {}, overlay)
        calibration = scene.pop("calibration", None)
        optics = dict(scene.get("optics") or {})
        if calibration is not None:
            _check_calibration(calibration, optics, label, ctx)
        measure = None
        if base_measure is not None or measure_overlay is not None:
            measure = deep_merge(base_measure or {}, measure_overlay or {})
        ctx.validate("scene", scene, label)
        ctx.validate("optics", optics, f"{label}.optics")
        if measure is not None:
            ctx.validate("measure", measure, f"{prefix}.measure" if overlays else "measure")
        out.append(
            SceneConfig(
                name=name, scene=scene, optics=optics, measure=measure, calibration=calibration
            )
        )
    return out


def _check_calibration(calibration, optics: Mapping, label: str, ctx: _Context) -> None:
    """A scene's calibration table: a table, a distortion to calibrate, no second product."""
    key = f"{label}.calibration"
    if not isinstance(calibration, Mapping):
        raise ConfigError(f"expected a table, got {calibration!r}", key=key, source=ctx.src)
    distortion = optics.get("distortion") or {}
    if distortion.get("calibration"):
        raise ConfigError(
            "the scene names a calibration product in optics.distortion.calibration and has a "
            f"[{key}] table; expected one of the two{ctx.suffix}",
            key=key,
            source=ctx.src,
        )
    if distortion.get("enabled", True) is False:
        raise ConfigError(
            f"a calibration needs a distortion: optics.distortion.enabled is false{ctx.suffix}",
            key=key,
            source=ctx.src,
        )
    ctx.validate("calibration", calibration, key)
