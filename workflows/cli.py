"""The ``mavispm`` command line.

Each stage contributes its sub-commands through a module with a
``register(subparsers)`` function that adds one argparse parser and sets
``func`` (a callable taking the parsed ``argparse.Namespace`` and returning an
exit code). This module only assembles them; it holds no stage logic.

Errors derived from :class:`~mavispm.core.errors.MavispmError` are printed as
one clear line (exit status 2) instead of a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from mavispm import __version__
from mavispm.core.errors import MavispmError

__all__ = [
    "COMMANDS",
    "COMMAND_MODULES",
    "KEEP_FREED_MEMORY",
    "ONE_BLAS_THREAD",
    "OneLineParser",
    "build_parser",
    "command_key",
    "main",
    "modules_for",
]

#: (group, module) pairs. ``group`` is None for top-level commands, otherwise
#: the name of the command group the module's parser is added under.
COMMAND_MODULES: list[tuple[str | None, str]] = [
    ("simulate", "mavispm.simulate.cluster.cli"),
    ("simulate", "mavispm.simulate.optics.cli"),
    ("simulate", "mavispm.simulate.optics.calibration_cli"),
    ("simulate", "mavispm.simulate.render.cli"),
    ("measure", "mavispm.measure.stars.cli"),
    ("measure", "mavispm.measure.propermotions.cli"),
    (None, "mavispm.dynamics.cli"),
    (None, "mavispm.dynamics.fast_stars_cli"),
    (None, "mavispm.workflows.runner_cli"),
    (None, "mavispm.workflows.cache_cli"),
    (None, "mavispm.workflows.export_cli"),
]

#: The command each module registers, by (group, name): running one command imports only
#: its own module (the others pull in photutils, matplotlib, scipy.stats, ... for ~1-4 s
#: of CPU); ``--help`` and unknown commands assemble everything.
COMMANDS: dict[tuple[str | None, str], str] = {
    ("simulate", "cluster"): "mavispm.simulate.cluster.cli",
    ("simulate", "optics"): "mavispm.simulate.optics.cli",
    ("simulate", "calibration"): "mavispm.simulate.optics.calibration_cli",
    ("simulate", "frames"): "mavispm.simulate.render.cli",
    ("measure", "stars"): "mavispm.measure.stars.cli",
    ("measure", "propermotions"): "mavispm.measure.propermotions.cli",
    (None, "dynamics"): "mavispm.dynamics.cli",
    (None, "fast-stars"): "mavispm.dynamics.fast_stars_cli",
    (None, "run"): "mavispm.workflows.runner_cli",
    (None, "report"): "mavispm.workflows.runner_cli",
    (None, "cache"): "mavispm.workflows.cache_cli",
    (None, "export"): "mavispm.workflows.export_cli",
}

GROUP_HELP = {
    "simulate": "simulate cluster catalogues, optics and frames",
    "measure": "measure stars in frames and proper motions across epochs",
}


class OneLineParser(argparse.ArgumentParser):
    """An argument parser whose usage errors are one line (exit status 2).

    ``mavispm run: error: argument --workers: ...; see 'mavispm run --help'``
    instead of the usage block. Sub-command parsers inherit the class.
    """

    def error(self, message: str):
        """Exit with status 2 and a one-line usage error.

        Parameters
        ----------
        message : str
            argparse's message.
        """
        self.exit(2, f"{self.prog}: error: {message} (see '{self.prog} --help')\n")


#: Commands whose program keeps the memory it frees for its next arrays
#: (:mod:`mavispm.core.malloc_policy`; measured on them: fewer fresh pages, less system time).
KEEP_FREED_MEMORY: set[tuple[str | None, str]] = {("simulate", "frames")}

#: Commands whose program loads OpenBLAS with one thread unless the environment sets a
#: count (:mod:`mavispm.core.blas_threads`; no large products: the idle workers'
#: busy-waiting cost ~0.26 s of CPU of a 10,000-star frame on 2 cores).
ONE_BLAS_THREAD: set[tuple[str | None, str]] = {("simulate", "frames")}


def command_key(argv: list[str] | None) -> tuple[str | None, str] | None:
    """The ``(group or None, command)`` that ``argv`` names (None: no words).

    Parameters
    ----------
    argv : list of str or None
        Command-line words (None: ``sys.argv[1:]``).

    Returns
    -------
    tuple or None
        E.g. ``("simulate", "frames")`` or ``(None, "run")``; not checked against
        :data:`COMMANDS`.
    """
    words = list(sys.argv[1:] if argv is None else argv)
    if words and words[0] in GROUP_HELP and len(words) > 1:
        return (words[0], words[1])
    if words:
        return (None, words[0])
    return None


def modules_for(argv: list[str] | None) -> list[tuple[str | None, str]]:
    """The (group, module) pairs needed to parse ``argv``: one for a known command, else all.

    Parameters
    ----------
    argv : list of str or None
        Command-line words (None: ``sys.argv[1:]``).

    Returns
    -------
    list of tuple
        ``(group or None, module name)`` pairs.
    """
    key = command_key(argv)
    module = COMMANDS.get(key)
    if module is None:
        return COMMAND_MODULES
    return [(group, m) for group, m in COMMAND_MODULES if m == module and group == key[0]]


def build_parser(argv: list[str] | None = None, everything: bool = True) -> argparse.ArgumentParser:
    """Assemble the argument parser from the stage modules.

    ``everything=False``: only the module of the command ``argv`` names (see
    :data:`COMMANDS`), so that running one stage does not import the others.

    Parameters
    ----------
    argv : list of str or None
        Command-line words (None: ``sys.argv[1:]``); only read when ``everything`` is False.
    everything : bool
        Register every command (for ``--help``); False: only the one ``argv`` names.

    Returns
    -------
    argparse.ArgumentParser
        The ``mavispm`` parser.
    """
    parser = OneLineParser(
        prog="mavispm",
        description="MAVIS MCAO proper-motion pipeline: simulate, measure, "
        "proper motions, dynamics.",
    )
    parser.add_argument("--version", action="version", version=f"mavispm {__version__}")
    top = parser.add_subparsers(dest="command", metavar="COMMAND")
    groups: dict[str, argparse._SubParsersAction] = {}
    for group, module_name in COMMAND_MODULES if everything else modules_for(argv):
        module = importlib.import_module(module_name)
        if group is None:
            module.register(top)
            continue
        if group not in groups:
            gp = top.add_parser(
                group, help=GROUP_HELP.get(group), description=GROUP_HELP.get(group)
            )
            groups[group] = gp.add_subparsers(dest=f"{group}_command", metavar="SUBCOMMAND")
            gp.set_defaults(func=_help_of(gp))
        module.register(groups[group])
    parser.set_defaults(func=_help_of(parser))
    return parser


def _help_of(parser: argparse.ArgumentParser):
    def show(_args) -> int:
        parser.print_help()
        return 0

    return show


def _freeze_imports() -> None:
    """Leave the objects alive now (the imported modules) out of the cyclic collector.

    They live until the process ends, yet every full collection traverses them, and
    so does the last one at exit: ~0.2 s of CPU of a 3 s ``simulate frames`` process
    (perf, 3,500 stars). Only done for the program, whose process ends with the command.
    The program also keeps the collector off while it imports (:func:`main`): the
    collections the imports' allocations would trigger traverse objects frozen here
    anyway (~0.03-0.05 s of CPU); the few cyclic objects the imports leave unreachable
    (~1,500, a few hundred KB) are frozen with them. The collector is on again after.
    """
    import gc

    gc.freeze()
    gc.enable()


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``mavispm`` console script.

    Parameters
    ----------
    argv : list of str or None
        Command-line words (None: ``sys.argv[1:]``, the program, which also: keeps the
        cyclic garbage collector off while the command's modules are imported and then
        freezes their objects out of it, ``gc.freeze``; loads numba's BLAS module without
        ``scipy.linalg``, :mod:`mavispm.core.blas_preload`; for the commands of
        :data:`ONE_BLAS_THREAD`, loads OpenBLAS with one thread unless the environment sets
        a count, :mod:`mavispm.core.blas_threads`; imports ``astropy.table``
        without its file-format connectors until ``Table.read`` / ``write`` needs them,
        :mod:`mavispm.core.table_preload`; loads numba's cached kernels before its
        compiler registries and lets numba's config import PyYAML only for a config file,
        :mod:`mavispm.core.numba_start`; for the commands of
        :data:`KEEP_FREED_MEMORY`, keeps the memory it frees for its next arrays,
        :mod:`mavispm.core.malloc_policy`).

    Returns
    -------
    int
        Exit status: 0 on success, 2 on bad input (one line on stderr).
    """
    if argv is None:  # the mavispm program: numba's BLAS check without scipy.linalg
        import gc

        gc.disable()  # while importing: see _freeze_imports
        from mavispm.core.blas_preload import load_cython_blas_alone
        from mavispm.core.blas_threads import one_blas_thread
        from mavispm.core.malloc_policy import keep_freed_memory
        from mavispm.core.numba_start import defer_numba_yaml, load_cached_kernels_first
        from mavispm.core.table_preload import import_table_without_connectors

        key = command_key(None)
        if key in ONE_BLAS_THREAD:
            one_blas_thread()  # before numpy and scipy load their OpenBLAS
        if key in KEEP_FREED_MEMORY:
            keep_freed_memory()
        load_cython_blas_alone()
        import_table_without_connectors()
        load_cached_kernels_first()
        defer_numba_yaml()
    try:
        parser = build_parser(argv, everything=False)
        args = parser.parse_args(argv)
    except SystemExit as exc:  # a usage error (one line, already printed): exit status 2
        if exc.code in (0, None):  # --help, --version
            raise
        return 2
    finally:
        if argv is None:  # the mavispm program (not a call from Python): see _freeze_imports
            _freeze_imports()
    try:
        return int(args.func(args) or 0)
    except MavispmError as exc:
        # one line, whatever a library put into the message (HDF5 errors hold newlines)
        print(f"mavispm: error: {' '.join(str(exc).split())}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("mavispm: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
