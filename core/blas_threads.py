"""One OpenBLAS thread for the commands that make no large matrix products (program start-up).

numpy and scipy each bring an OpenBLAS library (numpy's loads with numpy, scipy's with
``scipy.linalg.cython_blas``, which numba imports), and each starts one worker thread per
further core when it loads. A worker busy-waits for work after it starts and after every
product large enough to be split, before it sleeps: on the 2-core benchmark machine the two
workers took ~0.26 s of CPU of a 10,000-star ``mavispm simulate frames`` process (a
``perf`` profile: 12 % of its samples in ``blas_thread_server``), whatever
``render.threads``; the command's products are small (2 x 2 eigenvalues, the bilinear
weights). The count is read when a library loads, so it is set before numpy is imported.

Only the ``mavispm`` program calls :func:`one_blas_thread` (``workflows/cli.py``:
``main()`` reading ``sys.argv``, for the commands of ``ONE_BLAS_THREAD``); library callers
and an environment that sets a thread count are not affected.
"""

from __future__ import annotations

import os
import sys

__all__ = ["BLAS_THREAD_VARIABLES", "one_blas_thread"]

#: Environment variables OpenBLAS reads for its thread count (in this order of precedence).
BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "GOTO_NUM_THREADS", "OMP_NUM_THREADS")


def one_blas_thread() -> bool:
    """Set ``OPENBLAS_NUM_THREADS=1`` unless a thread count is set or numpy is loaded.

    Returns
    -------
    bool
        Whether the variable was set here.
    """
    if "numpy" in sys.modules or any(v in os.environ for v in BLAS_THREAD_VARIABLES):
        return False
    os.environ["OPENBLAS_NUM_THREADS"] = "1"
    return True
