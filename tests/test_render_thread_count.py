"""The automatic thread count of a frame (``render.threads = 0``).

* the rule: a count is used as given; 0 gives one thread below ``AUTO_MIN_STARS`` stars
  and every core from there; a negative count is refused;
* ``render_stack`` with the default settings renders a small frame's stamps and draws
  its noise on one thread, a frame at the threshold on every core (the spied thread
  pools and the noise draw's argument, with four usable cores), and the two
  frames are the same bit for bit.
"""

from __future__ import annotations

import concurrent.futures

import astropy.units as u
import numpy as np
import pytest

from mavispm.core import cores
from mavispm.simulate.render import stamps, thread_count
from mavispm.simulate.render.thread_count import AUTO_MIN_STARS, frame_threads


def test_rule(monkeypatch):
    monkeypatch.setattr(cores.os, "sched_getaffinity", lambda pid: set(range(6)), raising=False)
    assert frame_threads(3, 10) == 3
    assert frame_threads(1, 10 * AUTO_MIN_STARS) == 1
    assert frame_threads(0, 0) == 1
    assert frame_threads(0, AUTO_MIN_STARS - 1) == 1
    assert frame_threads(0, AUTO_MIN_STARS) == 6
    monkeypatch.setattr(cores.os, "sched_getaffinity", lambda pid: {0}, raising=False)
    assert frame_threads(0, AUTO_MIN_STARS) == 1
    with pytest.raises(ValueError, match="render.threads"):
        frame_threads(-1, 10)


def test_render_stack_threads_follow_the_star_count(monkeypatch):
    from render_helpers import random_epoch, tiptilt_halo_optics

    from mavispm.simulate.render import cli, frame
    from mavispm.simulate.render.scene import scene_from_mapping

    monkeypatch.setattr(cores.os, "sched_getaffinity", lambda pid: set(range(4)), raising=False)
    pools, draws = [], []

    class Pool(concurrent.futures.ThreadPoolExecutor):
        def __init__(self, max_workers=None, **kw):
            pools.append(max_workers)
            super().__init__(max_workers=max_workers, **kw)

    plain = frame.expose_stack

    def expose(*a, **k):
        draws.append(k["threads"])
        return plain(*a, **k)

    monkeypatch.setattr(stamps, "ThreadPoolExecutor", Pool)
    monkeypatch.setattr(frame, "expose_stack", expose)
    optics = tiptilt_halo_optics()
    scene = scene_from_mapping({"detector": {"nx": 256, "ny": 256}, "nexp": 4})
    assert scene.render.threads == 0  # the default: automatic
    n = 80
    t = random_epoch(n, 0.9)
    args = (t, 0.0 * u.yr, scene, optics)
    small = frame.render_stack(*args, cli.epoch_rng(5, "e0"), noiseless=False)
    assert pools and set(pools) == {1} and draws == [1]
    pools.clear()
    monkeypatch.setattr(thread_count, "AUTO_MIN_STARS", n)  # this frame is now "large"
    large = frame.render_stack(*args, cli.epoch_rng(5, "e0"), noiseless=False)
    assert pools and set(pools) == {4} and draws == [1, 4]
    np.testing.assert_array_equal(small.adu.view(np.uint32), large.adu.view(np.uint32))
