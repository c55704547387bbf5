"""numpy's PCG64 stepped inside compiled code (simulate/render/pcg64.py) against numpy itself."""

from __future__ import annotations

import zlib

import numba
import numpy as np
import pytest
from render_helpers import chunk_normals

from mavispm.simulate.render import pcg64

#: The first noise chunk of epoch "e0", seed 0, as the frames command spawns it.
_FRAMES_E0_CHUNK0 = np.random.SeedSequence([0, zlib.crc32(b"e0")]).spawn(1)[0]


@numba.njit
def _raw_uint32(state, n):
    out = np.empty(n, dtype=np.uint32)
    hi, lo, inc_hi, inc_lo, has, upper = state[0], state[1], state[2], state[3], state[4], state[5]
    for i in range(n):
        out[i], hi, lo, has, upper = pcg64._next_uint32(hi, lo, has, upper, inc_hi, inc_lo)
    state[0], state[1], state[4], state[5] = hi, lo, has, upper
    return out


@pytest.mark.parametrize("seed", [0, 12345, _FRAMES_E0_CHUNK0])
def test_compiled_steps_give_numpys_raw_stream(seed):
    ours, numpys = np.random.Generator(np.random.PCG64(seed)), np.random.PCG64(seed)
    state = pcg64.pcg64_take(ours)
    got = _raw_uint32(state, 20_000)  # the low half of each 64-bit output, then the high
    raw = numpys.random_raw(10_000).astype(np.uint64)
    want = np.empty(20_000, dtype=np.uint32)
    want[0::2] = raw & np.uint64(0xFFFFFFFF)
    want[1::2] = raw >> np.uint64(32)
    np.testing.assert_array_equal(got, want)
    pcg64.pcg64_put(ours, state)
    assert ours.bit_generator.random_raw() == numpys.random_raw()


@pytest.mark.parametrize("seed", [0, 1, _FRAMES_E0_CHUNK0])
@pytest.mark.parametrize("n", [2_000_001, 7])
def test_compiled_float32_normals_are_numpys(seed, n):
    # ~2e6 draws pass through the ziggurat's wedge and tail tests many times
    ours = np.random.Generator(np.random.PCG64(seed))
    numpys = np.random.Generator(np.random.PCG64(seed))
    state = pcg64.pcg64_take(ours)
    z = np.empty(n, dtype=np.float32)
    pcg64.standard_normals_f32_pcg64(state, z)
    pcg64.pcg64_put(ours, state)
    np.testing.assert_array_equal(z, numpys.standard_normal(n, dtype=np.float32))
    # the generator continues where numpy's would (its buffered 32-bit half included)
    assert ours.bit_generator.state == numpys.bit_generator.state
    assert (
        ours.integers(0, 2**32, 5, dtype=np.uint32).tolist()
        == numpys.integers(0, 2**32, 5, dtype=np.uint32).tolist()
    )
    assert ours.random() == numpys.random()


def test_a_buffered_half_is_drawn_first():
    # a state whose next 32-bit draw is the buffered upper half of the last output
    numpys = np.random.Generator(np.random.PCG64(3))
    numpys.integers(0, 2**32, 1, dtype=np.uint32)
    assert numpys.bit_generator.state["has_uint32"] == 1
    ours = np.random.Generator(np.random.PCG64())
    ours.bit_generator.state = numpys.bit_generator.state
    got = chunk_normals(ours, 100_000)
    np.testing.assert_array_equal(got, numpys.standard_normal(100_000, dtype=np.float32))
    assert ours.bit_generator.state == numpys.bit_generator.state


@pytest.mark.parametrize("bit_generator", [np.random.MT19937, np.random.PCG64DXSM, np.random.SFC64])
def test_other_bit_generators_draw_numpys_normals(bit_generator):
    assert pcg64.pcg64_take(np.random.Generator(bit_generator(0))) is None
    ours, numpys = np.random.Generator(bit_generator(4)), np.random.Generator(bit_generator(4))
    got = chunk_normals(ours, 10_001)
    np.testing.assert_array_equal(got, numpys.standard_normal(10_001, dtype=np.float32))
    assert ours.random() == numpys.random()
