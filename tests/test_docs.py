"""Documentation floor (issue 19, item 8): numpydoc coverage, ``__all__``, doctested examples.

The coverage is counted from the source text by ``benchmarks/doc_coverage.py`` (nothing is
imported), so this test takes well under a second; it fails when new public code lowers the
share of public callables with a numpydoc ``Parameters`` section below 90 %.
"""

from __future__ import annotations

import ast
import doctest
import importlib
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

import doc_coverage  # noqa: E402

#: Share of public callables with a numpydoc Parameters section (or no arguments) [percent].
COVERAGE_FLOOR = 90.0


@pytest.fixture(scope="module")
def coverage():
    return doc_coverage.scan_package(ROOT)


def test_numpydoc_coverage_is_at_least_90_percent(coverage):
    """At least 90 % of public callables document their parameters; the message lists what
    lacks a section."""
    missing = [f"{c.module}.{c.name}" for c in coverage.callables if not c.documented]
    assert len(coverage.callables) > 500  # the scan found the package
    assert coverage.percent >= COVERAGE_FLOOR, (
        f"numpydoc coverage {coverage.percent:.1f}% < {COVERAGE_FLOOR}%; missing: {missing}"
    )


def test_every_public_module_lists_its_names_in___all__(coverage):
    """Every public module that defines a public name has ``__all__``, and every name in it
    exists in the module (defined or imported)."""
    lacking = sorted(set(coverage.modules) - set(coverage.modules_with_all))
    assert not lacking, f"modules without __all__: {lacking}"
    for path in doc_coverage.public_modules(ROOT):
        tree = ast.parse(path.read_text())
        bound: set[str] = set()
        listed: list[str] = []
        for node in ast.walk(tree):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                bound.add(node.name)
            elif isinstance(node, ast.Name) and isinstance(node.ctx, ast.Store):
                bound.add(node.id)
            elif isinstance(node, ast.alias):
                bound.add((node.asname or node.name).split(".")[0])
        for node in tree.body:
            if isinstance(node, ast.Assign) and any(
                isinstance(t, ast.Name) and t.id == "__all__" for t in node.targets
            ):
                listed = [e.value for e in node.value.elts if isinstance(e, ast.Constant)]
        lazy = any(isinstance(n, ast.FunctionDef) and n.name == "__getattr__" for n in tree.body)
        unknown = [n for n in listed if n not in bound]
        assert lazy or not unknown, f"{path.relative_to(ROOT)}: __all__ names {unknown} undefined"


def test_the_scanner_counts_a_missing_section(tmp_path):
    """The scanner is not vacuous: an undocumented function with arguments counts as
    missing, a documented one and an argument-free one with a docstring as covered."""
    (tmp_path / "pkg").mkdir()
    (tmp_path / "pkg" / "mod.py").write_text(
        'def bare(x):\n    """No sections."""\n\n\n'
        'def good(x):\n    """Sum.\n\n    Parameters\n    ----------\n    x : float\n'
        '        A value [arcsec].\n    """\n\n\n'
        'def nothing():\n    """No arguments."""\n\n\n'
        "def _private(x):\n    pass\n"
    )
    module, callables, has_all = doc_coverage.scan_module(tmp_path / "pkg" / "mod.py", tmp_path)
    assert module == "pkg.mod" and not has_all
    assert {c.name: c.documented for c in callables} == {
        "bare": False,
        "good": True,
        "nothing": True,
    }
    (tmp_path / "pkg" / "wrong.py").write_text(
        'def f(x, y):\n    """F.\n\n    Parameters\n    ----------\n    x, z : float\n'
        '        Values.\n    """\n'
    )
    (mismatch,) = doc_coverage.parameter_mismatches(tmp_path)
    assert "undocumented ['y'] unknown ['z']" in mismatch


@pytest.mark.parametrize("module", ["mavispm.dynamics.jeans"])
def test_dynamics_docstring_example(module):
    """The dynamics stage's example (an isotropic Plummer sphere's projected dispersion
    against its closed form) runs as written."""
    result = doctest.testmod(importlib.import_module(module), optionflags=doctest.ELLIPSIS)
    assert result.attempted >= 5 and result.failed == 0


def test_parameters_sections_name_the_signature_arguments():
    """Where a function has a Parameters section, it documents exactly the arguments of its
    signature (no argument forgotten, none that does not exist)."""
    assert doc_coverage.parameter_mismatches(ROOT) == []
