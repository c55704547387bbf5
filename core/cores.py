"""The cores this process may run on: the one answer every "0 = all cores" knob uses.

``render.threads``, the stars stage's ``threads``, the render's FFT and noise pools and
the workflow's default worker count all read "0" as "every core". On Linux a process
may be confined to fewer cores than the machine has (``taskset``, a container's CPU
set, a batch scheduler's allocation); ``os.sched_getaffinity`` knows that mask where
``os.cpu_count`` counts the machine.
"""

from __future__ import annotations

import os

__all__ = ["usable_cores"]


def usable_cores() -> int:
    """Cores this process may run on (its affinity mask; ``os.cpu_count()`` without one).

    Returns
    -------
    int
        At least 1.
    """
    try:
        return max(len(os.sched_getaffinity(0)), 1)
    except (AttributeError, OSError):  # not on every platform
        return max(os.cpu_count() or 1, 1)
