"""On-disk array caches: round trip (memory-mapped and read members), bad files are misses."""

import zipfile

import numpy as np
import pytest

from mavispm.core.array_cache import MAP_MIN_BYTES, load_arrays, save_arrays


def _arrays():
    rng = np.random.default_rng(1)
    big = rng.normal(size=(3, MAP_MIN_BYTES // 16 + 7)) + 1j * rng.normal(size=(1,))
    return {
        "big": big.astype(np.complex128),  # mapped
        "big_f": np.asfortranarray(rng.normal(size=(400, 400))),  # mapped, Fortran order
        "small": np.arange(10, dtype=np.int64),
        "scalar": np.asarray(7.5),
        "empty": np.zeros((0, 3)),
    }


def test_round_trip_maps_large_members_read_only(tmp_path):
    arrays = _arrays()
    assert save_arrays(tmp_path / "a.npz", arrays)
    out = load_arrays(tmp_path / "a.npz")
    assert set(out) == set(arrays)
    for name, a in arrays.items():
        assert out[name].dtype == a.dtype and out[name].shape == a.shape
        np.testing.assert_array_equal(out[name], a)
    assert isinstance(out["big"], np.memmap) and not out["big"].flags.writeable
    assert isinstance(out["big_f"], np.memmap) and out["big_f"].flags.f_contiguous
    assert not isinstance(out["small"], np.memmap)
    # numpy's own reader agrees (the file is a plain .npz)
    with np.load(tmp_path / "a.npz") as ref:
        for name in arrays:
            np.testing.assert_array_equal(ref[name], out[name])


def test_compressed_members_are_read(tmp_path):
    arrays = _arrays()
    np.savez_compressed(tmp_path / "c.npz", **arrays)
    out = load_arrays(tmp_path / "c.npz")
    for name, a in arrays.items():
        np.testing.assert_array_equal(out[name], a)


@pytest.mark.parametrize("keep", [0, 100, 5000, -100])
def test_missing_or_truncated_files_are_misses(tmp_path, keep):
    save_arrays(tmp_path / "a.npz", _arrays())
    data = (tmp_path / "a.npz").read_bytes()
    bad = tmp_path / "bad.npz"
    bad.write_bytes(data[:keep] if keep else b"")
    assert load_arrays(bad) is None
    assert load_arrays(tmp_path / "missing.npz") is None


def test_member_cut_short_inside_a_valid_zip_is_a_miss(tmp_path):
    """A zip whose .npy header promises more bytes than the member holds."""
    header = tmp_path / "h.npy"
    np.save(header, np.zeros(MAP_MIN_BYTES // 8 + 100))
    raw = header.read_bytes()
    with zipfile.ZipFile(tmp_path / "z.npz", "w", zipfile.ZIP_STORED) as zf:
        zf.writestr("x.npy", raw[: len(raw) - 400])
    assert load_arrays(tmp_path / "z.npz") is None
