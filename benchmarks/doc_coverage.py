"""Documentation coverage of the mavispm package (issue 19, item 8).

Counts, from the source text alone (nothing is imported), the public callables of every public
module and how many of them carry a numpydoc ``Parameters`` section.

Rules
-----
- A module is public when no part of its path starts with ``_``; ``tests/`` and ``benchmarks/``
  are not part of the package.
- A public callable is a module-level function or class whose name does not start with ``_``,
  or a method of a public class whose name does not start with ``_`` (``__init__`` and
  ``__call__`` count as the class's own documentation, see below).
- A callable *needs* a ``Parameters`` section when it takes at least one argument besides
  ``self``/``cls``. For a class the arguments are those of its constructor: the explicit
  ``__init__`` or, for a dataclass, its annotated fields. A class's section may sit in the class
  docstring or in its ``__init__`` docstring (numpydoc allows both); a dataclass's fields are
  its constructor's arguments, so they belong in ``Parameters`` too (an ``Attributes``
  section alone does not count, as for numpydoc's own validator).
- A callable without arguments is covered when it has any docstring.
- Type hints: the share of arguments (besides ``self``/``cls``) of public functions and methods
  that carry an annotation.
- ``__all__``: every public module that defines (or, for a package ``__init__``, re-exports)
  a public name must list its public names in ``__all__``.

Run ``python benchmarks/doc_coverage.py`` (add ``--missing`` to list what lacks a section,
``--by-package`` for a per-package table).
"""

from __future__ import annotations

import argparse
import ast
import re
import sys
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

__all__ = [
    "Callable",
    "Coverage",
    "documented_parameters",
    "main",
    "parameter_mismatches",
    "scan_package",
]

ROOT = Path(__file__).resolve().parents[1]
EXCLUDED_TOP = {"tests", "benchmarks", "docs", ".dev", "build"}
_PARAMS = re.compile(r"^\s*Parameters\s*\n\s*-{3,}\s*$", re.MULTILINE)


@dataclass(frozen=True)
class Callable:
    """One public callable found in the source.

    Parameters
    ----------
    module : str
        Dotted module path inside the package, e.g. ``dynamics.jeans``.
    name : str
        Qualified name inside the module (``Class.method`` for methods).
    needs_params : bool
        True when the callable takes arguments besides ``self``/``cls``.
    documented : bool
        True when it is covered by the rules in the module docstring.
    n_args : int
        Number of arguments besides ``self``/``cls``.
    n_hinted : int
        How many of them carry a type annotation.
    """

    module: str
    name: str
    needs_params: bool
    documented: bool
    n_args: int
    n_hinted: int


@dataclass
class Coverage:
    """Coverage numbers of a set of modules.

    Parameters
    ----------
    callables : list of Callable
        Every public callable found.
    modules : list of str
        Every public module scanned.
    modules_with_all : list of str
        The modules that define ``__all__``.
    """

    callables: list[Callable] = field(default_factory=list)
    modules: list[str] = field(default_factory=list)
    modules_with_all: list[str] = field(default_factory=list)

    @property
    def n_documented(self) -> int:
        """Number of public callables covered."""
        return sum(c.documented for c in self.callables)

    @property
    def percent(self) -> float:
        """Share of public callables covered [percent]."""
        return 100.0 * self.n_documented / max(len(self.callables), 1)

    @property
    def percent_with_args(self) -> float:
        """Share of public callables that take arguments and have a Parameters section
        [percent]."""
        needing = [c for c in self.callables if c.needs_params]
        return 100.0 * sum(c.documented for c in needing) / max(len(needing), 1)

    @property
    def percent_hinted(self) -> float:
        """Share of arguments of public callables carrying a type hint [percent]."""
        n = sum(c.n_args for c in self.callables)
        return 100.0 * sum(c.n_hinted for c in self.callables) / max(n, 1)


def _arguments(node: ast.FunctionDef | ast.AsyncFunctionDef, method: bool) -> list[ast.arg]:
    a = node.args
    args = list(a.posonlyargs) + list(a.args) + list(a.kwonlyargs)
    if a.vararg is not None:
        args.append(a.vararg)
    if a.kwarg is not None:
        args.append(a.kwarg)
    is_static = any(isinstance(d, ast.Name) and d.id == "staticmethod" for d in node.decorator_list)
    if method and not is_static and args and args[0].arg in ("self", "cls"):
        args = args[1:]
    return args


def _has_params(doc: str | None) -> bool:
    return bool(doc) and bool(_PARAMS.search(doc))


def _is_dataclass(node: ast.ClassDef) -> bool:
    for d in node.decorator_list:
        target = d.func if isinstance(d, ast.Call) else d
        name = target.attr if isinstance(target, ast.Attribute) else getattr(target, "id", "")
        if name == "dataclass":
            return True
    return False


def _is_property(node: ast.FunctionDef) -> bool:
    for d in node.decorator_list:
        name = d.attr if isinstance(d, ast.Attribute) else getattr(d, "id", "")
        if name in ("property", "cached_property", "setter", "getter", "deleter"):
            return True
    return False


def _function(module: str, qual: str, node, method: bool) -> Callable:
    args = _arguments(node, method)
    doc = ast.get_docstring(node)
    needs = bool(args) and not _is_property(node)
    documented = _has_params(doc) if needs else bool(doc)
    return Callable(
        module, qual, needs, documented, len(args), sum(a.annotation is not None for a in args)
    )


def _class(module: str, node: ast.ClassDef) -> list[Callable]:
    out = []
    doc = ast.get_docstring(node)
    init = next(
        (n for n in node.body if isinstance(n, ast.FunctionDef) and n.name == "__init__"), None
    )
    if init is not None:
        n_args = len(_arguments(init, True))
        init_doc = ast.get_docstring(init)
        covered = _has_params(doc) or _has_params(init_doc)
    elif _is_dataclass(node):
        fields = [
            n
            for n in node.body
            if isinstance(n, ast.AnnAssign)
            and isinstance(n.target, ast.Name)
            and "ClassVar" not in ast.unparse(n.annotation)
        ]
        n_args = len(fields)
        covered = _has_params(doc)
    else:
        n_args = 0
        covered = _has_params(doc)
    needs = n_args > 0
    out.append(Callable(module, node.name, needs, covered if needs else bool(doc), 0, 0))
    for n in node.body:
        if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef)):
            if n.name.startswith("_"):
                continue
            if any(
                isinstance(d, ast.Attribute) and d.attr in ("setter", "deleter")
                for d in n.decorator_list
            ):
                continue
            out.append(_function(module, f"{node.name}.{n.name}", n, True))
    return out


def scan_module(path: Path, root: Path = ROOT) -> tuple[str, list[Callable], bool]:
    """Scan one source file.

    Parameters
    ----------
    path : pathlib.Path
        The ``.py`` file.
    root : pathlib.Path
        The package root (the repository root).

    Returns
    -------
    module : str
        Dotted module name relative to the root.
    callables : list of Callable
        The public callables it defines.
    has_all : bool
        Whether the module defines ``__all__`` (True also for a module that defines no
        public name, such as a docstring-only package ``__init__``: it has nothing to
        list).
    """
    rel = path.relative_to(root).with_suffix("")
    module = ".".join(rel.parts)
    tree = ast.parse(path.read_text(), filename=str(path))
    out: list[Callable] = []
    has_all = False
    exports = False  # defines or re-exports a public name (else it needs no __all__)
    for node in tree.body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            exports = exports or not node.name.startswith("_")
        elif isinstance(node, ast.ImportFrom) and path.name == "__init__.py":
            exports = exports or node.module != "__future__"
        if isinstance(node, (ast.Assign, ast.AnnAssign)):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            if any(isinstance(t, ast.Name) and t.id == "__all__" for t in targets):
                has_all = True
        elif isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            if not node.name.startswith("_"):
                out.append(_function(module, node.name, node, False))
        elif isinstance(node, ast.ClassDef) and not node.name.startswith("_"):
            out.extend(_class(module, node))
    return module, out, has_all or not exports


def public_modules(root: Path = ROOT) -> list[Path]:
    """List the package's public source files.

    Parameters
    ----------
    root : pathlib.Path
        The package root (the repository root).

    Returns
    -------
    list of pathlib.Path
        Every ``.py`` file outside ``tests/`` and ``benchmarks/`` with no path part starting
        with ``_`` (``__init__.py`` files are kept: they are the packages' faces).
    """
    files = []
    for p in sorted(root.rglob("*.py")):
        rel = p.relative_to(root)
        if rel.parts[0] in EXCLUDED_TOP or any(part.startswith(".") for part in rel.parts):
            continue
        if any(part.startswith("_") and part != "__init__.py" for part in rel.parts):
            continue
        files.append(p)
    return files


def scan_package(root: Path = ROOT) -> Coverage:
    """Scan every public module of the package.

    Parameters
    ----------
    root : pathlib.Path
        The package root (the repository root).

    Returns
    -------
    Coverage
        The callables found and the modules with ``__all__``.
    """
    cov = Coverage()
    for path in public_modules(root):
        module, callables, has_all = scan_module(path, root)
        cov.modules.append(module)
        if has_all:
            cov.modules_with_all.append(module)
        cov.callables.extend(callables)
    return cov


_SECTION = re.compile(
    r"^(Parameters|Other Parameters|Returns|Yields|Receives|Raises|Warns|Warnings|See Also|"
    r"Notes|References|Examples|Attributes|Methods)\n-{3,}$",
    re.MULTILINE,
)


def documented_parameters(doc: str) -> set[str] | None:
    """Names listed in a docstring's numpydoc ``Parameters`` section.

    Parameters
    ----------
    doc : str
        A cleaned docstring (``inspect.cleandoc``/``ast.get_docstring``).

    Returns
    -------
    set of str or None
        The names (``x, y : float`` gives two; ``*args`` gives ``args``); None without a
        Parameters section.
    """
    m = re.search(r"^Parameters\n-{3,}\n", doc, re.MULTILINE)
    if not m:
        return None
    rest = doc[m.end() :]
    nxt = _SECTION.search(rest)
    names = set()
    for line in (rest[: nxt.start()] if nxt else rest).splitlines():
        if line and not line.startswith(" "):
            for name in line.split(" :")[0].split(","):
                if name.strip().lstrip("*"):
                    names.add(name.strip().lstrip("*"))
    return names


def parameter_mismatches(root: Path = ROOT) -> list[str]:
    """Public functions whose Parameters section and signature name different arguments.

    Parameters
    ----------
    root : pathlib.Path
        The package root (the repository root).

    Returns
    -------
    list of str
        ``module:line name: undocumented [...] unknown [...]`` per mismatch.
    """
    out = []
    for path in public_modules(root):
        tree = ast.parse(path.read_text())
        methods = {id(f) for c in ast.walk(tree) if isinstance(c, ast.ClassDef) for f in c.body}
        for node in ast.walk(tree):
            if not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                continue
            names = documented_parameters(ast.get_docstring(node) or "")
            if names is None:
                continue
            args = {a.arg for a in _arguments(node, id(node) in methods)}
            if names != args:
                rel = path.relative_to(root)
                out.append(
                    f"{rel}:{node.lineno} {node.name}: undocumented {sorted(args - names)} "
                    f"unknown {sorted(names - args)}"
                )
    return out


def main(argv: list[str] | None = None) -> int:
    """Print the coverage numbers.

    Parameters
    ----------
    argv : list of str, optional
        Command-line arguments (default: ``sys.argv[1:]``).

    Returns
    -------
    int
        Exit status: 0.
    """
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--missing", action="store_true", help="list callables lacking a section")
    ap.add_argument("--by-package", action="store_true", help="table per top-level package")
    args = ap.parse_args(argv)
    cov = scan_package()
    if args.by_package:
        groups: dict[str, list[Callable]] = defaultdict(list)
        for c in cov.callables:
            parts = c.module.split(".")
            key = ".".join(parts[:2]) if parts[0] in ("simulate", "measure") else parts[0]
            groups[key].append(c)
        for key in sorted(groups):
            cs = groups[key]
            n = sum(c.documented for c in cs)
            print(f"{key:28s} {n:4d}/{len(cs):4d}  {100 * n / len(cs):5.1f}%")
    if args.missing:
        for c in cov.callables:
            if not c.documented:
                print(f"missing: {c.module}.{c.name}")
        for line in parameter_mismatches():
            print(f"mismatch: {line}")
    print(
        f"numpydoc coverage: {cov.n_documented}/{len(cov.callables)} public callables "
        f"({cov.percent:.1f}%); with arguments: {cov.percent_with_args:.1f}%"
    )
    print(f"type hints: {cov.percent_hinted:.1f}% of arguments")
    print(
        f"__all__: {len(cov.modules_with_all)}/{len(cov.modules)} public modules "
        "(a module defining no public name needs none)"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
