"""The stage registry: which function runs, validates and summarises each stage.

The workflow graph has a fixed shape (catalogue -> frames per epoch and scene ->
measured -> proper motions -> dynamics, with an optional optics PSF grid per
scene), but the functions behind each stage come from a :class:`StageRegistry`.
The default registry (:func:`mavispm.workflows.stages.default_registry`) wires
the real stage modules; tests register small stand-ins with the same names.

Functions are referred to by ``"module:function"`` strings so a task can be
pickled and sent to a worker process or a dask worker that imports them itself.

Adapter signatures
------------------
``run(inputs, settings, params, seed, outdir) -> dict[str, Path]``
    ``inputs`` maps an input name (``"catalogue"``, ``"psf"``, ``"frames"``,
    ``"measured"``, ``"propermotions"``) to a path or list of paths;
    ``settings`` is the stage's TOML table; ``params`` holds node parameters
    (epoch, scene name, output switches); ``outdir`` is an empty folder the stage
    writes into. Returns product name to path (all inside ``outdir``); the
    product named ``"main"`` feeds the downstream stages.
``validate(settings, source) -> object``
    Raises :class:`~mavispm.core.errors.ConfigError` for bad settings.
``summarize(products) -> dict``
    Scalar metrics of a finished node for summary.json and sweep tables.
``report(product_paths, outdir) -> list[Path]``
    A stage's accuracy report over all its products of a run.
"""

from __future__ import annotations

import hashlib
import importlib
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

__all__ = [
    "STAGE_NAMES",
    "StageRegistry",
    "StageSpec",
    "code_files",
    "resolve",
]

#: The stage names of the workflow graph, in pipeline order.
STAGE_NAMES = (
    "cluster",
    "optics",
    "calibration",
    "frames",
    "stars",
    "propermotions",
    "dynamics",
)

PACKAGE_ROOT = Path(__file__).resolve().parent.parent


def resolve(ref: str | None) -> Callable | None:
    """Import ``"module:function"`` and return the function.

    Parameters
    ----------
    ref : str or None
        ``"package.module:function"``.

    Returns
    -------
    callable or None
        The function; None when ``ref`` is None.

    Raises
    ------
    ImportError
        When the module or the function does not exist.
    """
    if ref is None:
        return None
    module_name, _, func_name = ref.partition(":")
    module = importlib.import_module(module_name)
    try:
        return getattr(module, func_name)
    except AttributeError:
        raise ImportError(f"module '{module_name}' has no function '{func_name}'") from None


@dataclass(frozen=True)
class StageSpec:
    """How the runner calls one stage.

    Parameters
    ----------
    name : str
        Stage name (one of :data:`STAGE_NAMES`).
    run : str
        ``"module:function"`` of the run adapter.
    validate : str or None
        ``"module:function"`` validating the stage settings.
    summarize : str or None
        ``"module:function"`` returning scalar metrics of a finished node.
    report : str or None
        ``"module:function"`` writing the stage's accuracy report.
    code : tuple of str
        Glob patterns, relative to the package root, of the source files whose
        content is part of every task key (editing them invalidates the cache);
        a pattern starting with ``!`` removes the files it matches (for example
        plotting code that no product depends on).
    version : str
        Extra version string folded into every task key.
    exclusive : bool
        Run at most one task of this stage at a time per process (for stages that
        are not thread-safe, such as those drawing with matplotlib's pyplot).
    ui_keys : tuple of str
        Dotted settings keys that change neither the results nor the products'
        data (progress bars, thread counts); they are left out of the task key,
        so toggling them reuses the cached products.
    canonical : str or None
        ``"module:function"``, called as ``f(settings, stage)`` with the stage's
        settings table and name, returning the table's one canonical spelling before it
        is hashed (the knobs moved to their home keys, so that
        ``[x.knobs] k = 1`` and ``[x] k = 1`` share a key); None: hashed as given.
    """

    name: str
    run: str
    validate: str | None = None
    summarize: str | None = None
    report: str | None = None
    code: tuple[str, ...] = ()
    version: str = ""
    exclusive: bool = False
    ui_keys: tuple[str, ...] = ()
    canonical: str | None = None

    def code_version(self) -> str:
        """Digest of the package version, ``version`` and the ``code`` files."""
        return _code_digest(self.code, self.version)


def code_files(patterns: Iterable[str]) -> list[Path]:
    """Source files matched by ``patterns`` (globs under the package root; ``!`` excludes).

    Parameters
    ----------
    patterns : iterable of str
        Glob patterns relative to the package root; one starting with ``!`` removes
        the files it matches.

    Returns
    -------
    list of pathlib.Path
        Sorted absolute paths.
    """

    def matches(pattern):
        return {p for p in PACKAGE_ROOT.glob(pattern) if p.is_file()}

    patterns = tuple(patterns)
    files = set().union(*(matches(pat) for pat in patterns if not pat.startswith("!")))
    files -= set().union(*(matches(pat[1:]) for pat in patterns if pat.startswith("!")))
    return sorted(files)


@lru_cache(maxsize=64)
def _code_digest(patterns: tuple[str, ...], version: str) -> str:
    from mavispm import __version__

    h = hashlib.sha256(f"{__version__}|{version}".encode())

    for path in code_files(patterns):
        h.update(str(path.relative_to(PACKAGE_ROOT)).encode())
        h.update(path.read_bytes())
    return h.hexdigest()[:16]


@dataclass
class StageRegistry:
    """Stage name to :class:`StageSpec`.

    Parameters
    ----------
    stages : dict of str to StageSpec
        The registered stages.
    """

    stages: dict[str, StageSpec] = field(default_factory=dict)

    @classmethod
    def of(cls, specs: Iterable[StageSpec]) -> StageRegistry:
        """Registry holding ``specs``.

        Parameters
        ----------
        specs : iterable of StageSpec
            The stages.

        Returns
        -------
        StageRegistry
            Keyed by stage name.
        """
        return cls({s.name: s for s in specs})

    def register(self, spec: StageSpec) -> None:
        """Add or replace a stage.

        Parameters
        ----------
        spec : StageSpec
            The stage (replaces one of the same name).
        """
        self.stages[spec.name] = spec

    def __contains__(self, name: str) -> bool:
        return name in self.stages

    def __getitem__(self, name: str) -> StageSpec:
        return self.stages[name]

    def validate(self, name: str, settings: Mapping, source: str | None = None):
        """Run the stage's settings validator (no-op when it has none).

        Parameters
        ----------
        name : str
            Stage name.
        settings : mapping
            The stage's settings table.
        source : str or None
            File named in error messages.

        Returns
        -------
        object or None
            What the validator returns (the validated settings), None without a validator.
        """
        func = resolve(self.stages[name].validate)
        return None if func is None else func(dict(settings), source=source)
