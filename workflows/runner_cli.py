"""``mavispm run WORKFLOW.toml`` and ``mavispm report RUNDIR``."""

from __future__ import annotations

import argparse
import contextlib
import logging
import sys
from pathlib import Path

from mavispm.core.cliargs import non_negative_int
from mavispm.workflows.runner import DEFAULT_WORKDIR

__all__ = [
    "configure_logging",
    "parse_overrides",
    "register",
]


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the ``run`` and ``report`` commands to the top-level sub-parsers.

    Parameters
    ----------
    subparsers : argparse._SubParsersAction
        The sub-parsers of the ``mavispm`` parser (or of its command group).
    """
    run = subparsers.add_parser(
        "run",
        help="run a workflow file (cached, resumable)",
        description="Run a whole study described by a workflow file. Products are cached by "
        "content: a second run does no work, a changed setting re-runs only what depends on it, "
        "and an interrupted run resumes. Shipped workflows (quickstart, astrometric_budget, "
        "ngc3201_imbh, pm_accuracy, imbh_detectability) can be named without a path.",
    )
    run.add_argument("workflow", help="workflow TOML file, or the name of a shipped workflow")
    run.add_argument(
        "--workdir",
        type=Path,
        default=Path(DEFAULT_WORKDIR),
        help=f"work directory holding the product store and run directories (default ./{DEFAULT_WORKDIR})",
    )
    run.add_argument(
        "--scheduler",
        default=None,
        metavar="ADDRESS",
        help="where tasks run (default: the workflow's [workflow] executor, threads unless set): "
        "threads, processes, serial, or the address of a running "
        "dask.distributed scheduler such as tcp://host:8786",
    )
    run.add_argument(
        "--workers",
        type=non_negative_int,
        default=None,
        help="local pool size (default: all CPUs)",
    )
    run.add_argument("--force", action="store_true", help="recompute every node even when cached")
    run.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a workflow key (dotted, TOML value), e.g. --set dynamics.max_steps=500 "
        "or --set 'scene.optics.tiptilt.asterism=\"bad\"' (repeatable)",
    )
    run.add_argument(
        "--dry-run",
        action="store_true",
        help="validate and list the nodes (cached / to run); run nothing",
    )
    noise = run.add_mutually_exclusive_group()
    noise.add_argument(
        "--quiet",
        action="store_true",
        help="no progress bars and no per-stage summary; only errors and the run directory",
    )
    noise.add_argument(
        "--verbose",
        action="store_true",
        help="log every node as it finishes, with the warnings it raised",
    )
    run.set_defaults(func=_run)

    report = subparsers.add_parser(
        "report",
        help="(re)write the report of a run directory",
        description="Write report.md with tables and plots from a run directory's summary.json "
        "and products, without running any stage.",
    )
    report.add_argument("rundir", type=Path, help="run directory (<workdir>/<workflow name>)")
    report.set_defaults(func=_report)


def parse_overrides(items: list[str]) -> dict:
    """``KEY=VALUE`` strings to a dict; values are TOML literals, else plain strings.

    Parameters
    ----------
    items : list of str
        ``--set`` arguments.

    Returns
    -------
    dict
        Dotted key to value.

    Raises
    ------
    ConfigError
        For an item without ``=``.
    """
    import tomllib

    from mavispm.core.errors import ConfigError

    out = {}
    for item in items:
        key, sep, text = item.partition("=")
        if not sep or not key.strip():
            raise ConfigError(f"expected KEY=VALUE, got {item!r}", key="--set")
        try:
            value = tomllib.loads(f"v = {text}")["v"]
        except tomllib.TOMLDecodeError:
            value = text
        out[key.strip()] = value
    return out


def _run(args: argparse.Namespace) -> int:
    from mavispm.workflows.config import load_workflow
    from mavispm.workflows.runner import plan_workflow, run_workflow
    from mavispm.workflows.stages import default_registry

    registry = default_registry()
    workflow = load_workflow(args.workflow, registry, overrides=parse_overrides(args.set))
    if args.dry_run:
        plan = plan_workflow(workflow, args.workdir, registry)
        for entry in plan:
            print(f"  {entry['status']:>7}  {entry['id']}")
        count = {s: sum(e["status"] == s for e in plan) for s in ("to run", "shared", "cached")}
        print(
            f"{len(plan)} nodes: {count['to run']} to run, {count['shared']} shared with an "
            f"identical node, {count['cached']} cached (nothing was run)"
        )
        return 0
    configure_logging(quiet=args.quiet, verbose=args.verbose)
    progress = not args.quiet and sys.stderr.isatty()
    redirect = contextlib.nullcontext()
    if progress:  # log lines above the bars instead of through them
        from tqdm.contrib.logging import logging_redirect_tqdm

        redirect = logging_redirect_tqdm(loggers=[logging.getLogger("mavispm")])
    with redirect:
        result = run_workflow(
            workflow,
            registry=registry,
            workdir=args.workdir,
            scheduler=args.scheduler,
            force=args.force,
            workers=args.workers,
            progress=progress,
        )
    print(f"run directory: {result.rundir}")
    if args.quiet:
        return 0
    for name, st in result.summary["stages"].items():
        print(f"  {name:>13}: {st['ran']} ran, {st['cached']} cached, {st['wall_s']:.1f} s")
    lost = result.summary.get("interrupted_tasks") or []
    if lost:
        print(f"  {len(lost)} task(s) redone after an attempt died (killed run or lost worker)")
    n_warn = sum(len(n.get("warnings", [])) for n in result.summary["nodes"])
    print(
        f"  total wall time {result.summary['wall_s']:.1f} s; report: {result.rundir / 'report.md'}"
        + (
            f"; {n_warn} library warning(s) recorded in summary.json and the report"
            if n_warn
            else ""
        )
    )
    return 0


def configure_logging(quiet: bool = False, verbose: bool = False) -> None:
    """Send the ``mavispm`` loggers to stderr: errors only (``quiet``), warnings
    (default) or every finished node with its warnings (``verbose``).

    Parameters
    ----------
    quiet, verbose : bool
        The ``--quiet`` and ``--verbose`` options.
    """
    logger = logging.getLogger("mavispm")
    logger.setLevel(logging.ERROR if quiet else logging.DEBUG if verbose else logging.WARNING)
    if not any(isinstance(h, _StderrHandler) for h in logger.handlers):
        handler = _StderrHandler()
        handler.setFormatter(logging.Formatter("mavispm: %(message)s"))
        logger.addHandler(handler)


class _StderrHandler(logging.StreamHandler):
    """A stream handler writing to whatever ``sys.stderr`` is when a record comes."""

    @property
    def stream(self):
        return sys.stderr

    @stream.setter
    def stream(self, value):  # StreamHandler.__init__ sets it; the property wins
        pass


def _report(args: argparse.Namespace) -> int:
    from mavispm.workflows.report import write_report

    path = write_report(args.rundir)
    print(f"report: {path}")
    return 0
