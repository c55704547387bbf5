"""``usable_cores``: the cores this process may run on, the answer of every "0 = all cores".

* against the operating system itself: a child process confined to one core by
  ``os.sched_setaffinity`` (as ``taskset`` or a batch scheduler confines it) gets 1,
  where ``os.cpu_count`` still counts the machine;
* without an affinity mask (not Linux) it falls back to ``os.cpu_count`` and never
  returns less than 1;
* the knobs that read "0" as every core (the render's thread count, the stars stage's
  chunk pools, the workflow's default worker count) follow it.
"""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from mavispm.core import cores
from mavispm.core.cores import usable_cores
from mavispm.measure.stars.chunk_pool import resolve_threads
from mavispm.simulate.render.thread_count import AUTO_MIN_STARS, frame_threads
from mavispm.workflows.executors import default_workers


@pytest.mark.skipif(not hasattr(os, "sched_setaffinity"), reason="no affinity masks here")
def test_a_process_confined_to_one_core_sees_one():
    code = (
        "import os; os.sched_setaffinity(0, {min(os.sched_getaffinity(0))}); "
        "from mavispm.core.cores import usable_cores; print(usable_cores(), os.cpu_count())"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    seen, machine = map(int, out.stdout.split())
    assert seen == 1
    assert machine == os.cpu_count()


def test_without_a_mask_the_machine_count_and_never_zero(monkeypatch):
    monkeypatch.delattr(cores.os, "sched_getaffinity", raising=False)
    monkeypatch.setattr(cores.os, "cpu_count", lambda: 5)
    assert usable_cores() == 5
    monkeypatch.setattr(cores.os, "cpu_count", lambda: None)
    assert usable_cores() == 1


def test_every_all_cores_knob_follows_it(monkeypatch):
    monkeypatch.setattr(cores.os, "sched_getaffinity", lambda pid: {2, 5, 7}, raising=False)
    monkeypatch.setattr(cores.os, "cpu_count", lambda: 64)
    assert usable_cores() == 3
    assert resolve_threads(0) == 3
    assert frame_threads(0, AUTO_MIN_STARS) == 3
    assert default_workers() == 3
    assert resolve_threads(2) == 2 and frame_threads(2, AUTO_MIN_STARS) == 2
