"""numba's BLAS module loaded without the scipy.linalg package (core/blas_preload.py).

Each check runs in a fresh interpreter: the point is what gets imported.
"""

from __future__ import annotations

import subprocess
import sys
import textwrap


def _run(code: str) -> list[str]:
    out = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True, timeout=300
    )
    assert out.returncode == 0, out.stderr[-2000:]
    return out.stdout.strip().splitlines()


def test_numba_without_the_preload_imports_scipy_linalg():
    """The premise: importing numba's array maths pulls in the whole scipy.linalg package
    (if a numba release stops doing so, the preload has nothing left to save)."""
    lines = _run(
        """
        import sys
        import numba.np.arraymath
        print("scipy.linalg" in sys.modules)
        """
    )
    assert lines[-1] == "True"


def test_preloaded_blas_serves_numba_and_a_later_scipy_linalg():
    """After the preload numba imports without scipy.linalg, its compiled BLAS calls give
    numpy's products, and a later ``import scipy.linalg`` works and holds the same module."""
    lines = _run(
        """
        import sys
        import numpy as np
        from mavispm.core.blas_preload import load_cython_blas_alone
        first = load_cython_blas_alone()
        again = load_cython_blas_alone()
        import numba
        import numba.np.arraymath
        print(first, again, "scipy.linalg" in sys.modules)

        @numba.njit
        def products(a, b):
            return np.dot(a, b), a @ b

        rng = np.random.default_rng(0)
        a, b = rng.normal(size=(5, 7)), rng.normal(size=(7, 3))
        d, m = products(a, b)
        print(np.allclose(d, a @ b, rtol=1e-13, atol=0), np.allclose(m, a @ b, rtol=1e-13, atol=0))
        import scipy.linalg
        from scipy.linalg import cython_blas
        print(scipy.linalg.cython_blas is sys.modules["scipy.linalg.cython_blas"] is cython_blas)
        x = scipy.linalg.solve(a[:5, :5], b[:5])
        print(np.allclose(a[:5, :5] @ x, b[:5]))
        """
    )
    assert lines[-4:] == ["True False False", "True True", "True", "True"]


def test_only_the_program_preloads():
    """``main()`` reading ``sys.argv`` preloads before the command's modules import numba;
    ``main(argv)`` called from Python leaves the imports alone."""
    code = """
        import sys
        from mavispm.workflows import cli
        sys.argv = ["mavispm"] + {argv}
        try:
            cli.main({call})
        except SystemExit:
            pass
        loaded = "numba" in sys.modules
        import numba.np.arraymath  # what the first compiled call imports
        print(loaded, "scipy.linalg" in sys.modules)
        """
    argv = ["simulate", "frames", "--help"]
    assert _run(code.format(argv=argv, call=""))[-1] == "True False"
    assert _run(code.format(argv=[], call=repr(argv)))[-1] == "True True"
