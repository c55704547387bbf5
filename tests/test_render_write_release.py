"""The frames image written and released page by page (helper render17).

``write_product(..., release=names)`` writes those arrays a block of rows at a time and
returns each block's memory pages to the kernel once written (``madvise``), so that the
output's page cache takes them instead of fresh pages; ``run_stage`` hands over its
stack's image. Checked against independent references: the file read back equals a copy
of the array taken before the write (and the file written without release), the kernel's
own count of the process's anonymous memory drops by the array's size, and arrays that
are not a numpy array's own writeable memory are written as usual and left intact.
"""

from __future__ import annotations

import mmap
import sys

import astropy.units as u
import h5py
import numpy as np
import pytest

from mavispm.core import products
from mavispm.core.malloc_policy import owns_memory, release_pages
from mavispm.core.products import read_product, write_product

linux_only = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="madvise zero-fill")


def _anonymous_kb() -> int:
    with open("/proc/self/smaps_rollup") as fh:
        for line in fh:
            if line.startswith("Anonymous:"):
                return int(line.split()[1])
    raise AssertionError("no Anonymous line")


@linux_only
def test_released_pages_go_back_to_the_kernel_and_read_as_zeros():
    n = 8 << 20  # 32 MB of float32, touched
    arr = np.ones(n, dtype=np.float32)
    before = _anonymous_kb()
    start, stop = 100, arr.nbytes - 100
    done = release_pages(arr, start, stop)
    after = _anonymous_kb()
    page = mmap.PAGESIZE
    base = arr.ctypes.data
    lo = -(-(base + start) // page) * page - base  # first whole page inside [start, stop)
    hi = (base + stop) // page * page - base
    assert done == hi - lo > arr.nbytes - 3 * page
    assert before - after > 0.9 * done / 1024  # the kernel's count, not ours
    raw = arr.view(np.uint8)
    ref = np.ones(n, dtype=np.float32).view(np.uint8)
    assert not raw[lo:hi].any()
    assert np.array_equal(raw[:lo], ref[:lo]) and np.array_equal(raw[hi:], ref[hi:])


def test_only_an_arrays_own_writeable_memory_is_released(tmp_path):
    owner = np.ones((64, 64), dtype=np.float32)
    assert owns_memory(owner)
    assert owns_memory(owner[8:16])  # rows: contiguous view of an owner
    assert owns_memory(u.Quantity(owner, u.adu, copy=False).value)
    assert not owns_memory(owner[:, :8])  # not contiguous
    frozen = owner.copy()
    frozen.flags.writeable = False
    assert not owns_memory(frozen)
    assert not owns_memory(np.frombuffer(bytearray(owner.tobytes()), dtype=np.float32))
    np.save(tmp_path / "m.npy", owner)
    assert not owns_memory(np.load(tmp_path / "m.npy", mmap_mode="r+"))
    with pytest.raises(ValueError):
        release_pages(np.frombuffer(bytearray(owner.tobytes()), dtype=np.float32), 0, 1 << 20)


@linux_only
@pytest.mark.parametrize("shape", [(3000, 700), (1, 5000), (17, 3)])
def test_released_array_is_written_whole_and_its_memory_returned(tmp_path, shape):
    rng = np.random.default_rng(7)
    image = rng.normal(100.0, 10.0, shape).astype(np.float32)
    truth = image.copy()
    mask = np.zeros(shape, dtype=bool)
    mask[0, -1] = True
    kept_mask = mask.copy()
    plain = write_product(tmp_path / "plain.h5", "frames", arrays={"image": image.copy()})
    out = write_product(
        tmp_path / "rel.h5",
        "frames",
        arrays={"image": u.Quantity(image, u.adu, copy=False), "saturated": mask},
        release=("image",),
    )
    got = read_product(out, "frames").arrays
    assert np.array_equal(got["image"].value, truth) and got["image"].unit == u.adu
    assert np.array_equal(got["saturated"], kept_mask)
    assert np.array_equal(mask, kept_mask)  # not named: left alone
    with h5py.File(plain) as a, h5py.File(out) as b:
        assert a["image"][()].tobytes() == b["image"][()].tobytes()
    if image.nbytes >= 3 * mmap.PAGESIZE:  # at least one whole page inside: released
        assert np.count_nonzero(image) * image.itemsize <= 2 * mmap.PAGESIZE


def test_memory_that_is_not_ours_is_written_and_left_intact(tmp_path):
    data = np.arange(4096 * 6, dtype=np.float32).reshape(96, 256)
    shared = np.frombuffer(data.tobytes(), dtype=np.float32).reshape(96, 256)  # read-only
    strided = data.copy()[:, ::2]
    out = write_product(
        tmp_path / "x.h5",
        "frames",
        arrays={"a": shared, "b": strided},
        release=("a", "b"),
    )
    got = read_product(out, "frames").arrays
    assert np.array_equal(got["a"], data) and np.array_equal(shared, data)
    assert np.array_equal(got["b"], data[:, ::2]) and np.array_equal(strided, data[:, ::2])
    # an array sharing memory with another of the product: written, not released
    owner = data.copy()
    out = write_product(
        tmp_path / "y.h5",
        "frames",
        arrays={"a": owner, "b": owner[10:20], "c": u.Quantity(owner, u.adu, copy=False)},
        release=("a",),
    )
    got = read_product(out, "frames").arrays
    assert np.array_equal(got["a"], data) and np.array_equal(got["b"], data[10:20])
    assert np.array_equal(got["c"].value, data) and np.array_equal(owner, data)


@linux_only
def test_run_stage_and_write_frame_release_only_their_own_image(tmp_path, monkeypatch):
    from render_helpers import random_epoch, tiptilt_halo_optics

    from mavispm.core.catalogue import Catalogue
    from mavispm.simulate.render import cli
    from mavispm.simulate.render.frame import render_frame, render_stack
    from mavispm.simulate.render.scene import scene_from_mapping

    monkeypatch.setattr(products, "RELEASE_BLOCK", 2 * mmap.PAGESIZE)  # several blocks
    optics = tiptilt_halo_optics()
    scene = scene_from_mapping({"detector": {"nx": 160, "ny": 150, "gain": 1.7}, "nexp": 4})
    t = random_epoch(20, 0.5)
    cat = Catalogue(epochs={"e0": t}, attrs={})
    args = (t, 0.0 * u.yr, scene, optics)
    want = render_stack(*args, cli.epoch_rng(5, "e0")).adu.copy()

    stack = render_stack(*args, cli.epoch_rng(5, "e0"))
    got = read_product(cli.write_frame(stack, tmp_path / "a.h5", scene, cat, 5), "frames")
    assert np.array_equal(got.arrays["image"].value, want)
    assert np.array_equal(stack.adu, want)  # not handed over: intact

    got = read_product(
        cli.write_frame(stack, tmp_path / "b.h5", scene, cat, 5, release=True), "frames"
    )
    assert np.array_equal(got.arrays["image"].value, want)
    assert np.count_nonzero(stack.adu) * 4 <= 2 * mmap.PAGESIZE  # handed over: released

    frame = render_frame(*args, cli.epoch_rng(5, "e0"))
    image = frame.image.copy()
    got = read_product(cli.write_frame(frame, tmp_path / "c.h5", scene, cat, 5), "frames")
    assert np.array_equal(got.arrays["image"].value, want)
    assert np.array_equal(frame.image, image)  # only the temporary adu was released

    # run_stage: the same file as writing the stack without release
    out = cli.run_stage(cat, "e0", {"detector": {"nx": 160, "ny": 150, "gain": 1.7}, "nexp": 4},
                        tmp_path / "d.h5", 5, optics=optics)  # fmt: skip
    assert np.array_equal(read_product(out, "frames").arrays["image"].value, want)
