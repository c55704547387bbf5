"""How many threads a frame is rendered on: ``render.threads``, or the automatic choice.

``render.threads = 0`` (the default) is automatic: frames with fewer than
:data:`AUTO_MIN_STARS` stars are rendered on one thread, larger ones on all cores. The
rendered frame is the same bit for bit on any number of threads; only the cost moves.

Measured on the benchmark's 2-core VM (``bench_render.py`` inputs: the 4000 x 4000
frame, every term on, whole ``mavispm simulate frames`` process, medians of 3 (6 at
10,000 stars) alternating runs, nothing else running; docs/render.md, "Automatic thread
count"):

======== ============================ =============================
stars    CPU, one -> two threads [s]  wall, one -> two threads [s]
======== ============================ =============================
3,500    1.29 -> 1.74                 1.32 -> 1.56
10,000   1.88 -> 2.32                 1.91 -> 1.80
30,000   3.27 -> 4.24                 3.30 -> 2.96
100,000  10.53 -> 11.34               10.60 -> 7.40
======== ============================ =============================

Below ~20,000 stars a second thread bought no wall time (the stamps' FFTs of two
threads take the caches from each other; the fixed costs are serial) and cost 0.4 s
of CPU; above, it saves 10-30 % of the wall time for 10-30 % more CPU. A workflow renders several epochs at
once on its own thread pool (``[workflow] executor``), where one thread per small frame
is the better use of the cores too.
"""

from __future__ import annotations

from mavispm.core.cores import usable_cores

__all__ = ["AUTO_MIN_STARS", "frame_threads"]

#: With ``render.threads = 0``, frames of fewer stars than this render on one thread.
AUTO_MIN_STARS = 20_000


def frame_threads(requested: int, n_stars: int) -> int:
    """Threads to render a frame of ``n_stars`` stars on.

    Parameters
    ----------
    requested : int
        ``render.threads``: a count (>= 1) is used as it is; 0 is automatic.
    n_stars : int
        Stars drawn in the frame.

    Returns
    -------
    int
        ``requested`` if >= 1; else 1 below :data:`AUTO_MIN_STARS` stars and the
        number of cores this process may use
        (:func:`~mavispm.core.cores.usable_cores`) from there.
    """
    if requested < 0:
        raise ValueError(f"render.threads must be >= 0 (0: automatic), got {requested}")
    if requested:
        return int(requested)
    if n_stars < AUTO_MIN_STARS:
        return 1
    return usable_cores()
