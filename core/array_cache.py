"""Small on-disk caches of named arrays (``.npz`` files), written atomically.

For results that are expensive but pure functions of their inputs: the renderer's
stamp plans (the PSF-node transforms) and the optics' seeing-halo profile, which
every epoch of a scene (every ``frames`` node of a workflow, each in its own
process) would otherwise recompute. The caller names the folder (nothing is
cached unless it does) and builds the key from everything the content depends
on; a missing or unreadable file is a miss, and a folder that cannot be written
only costs the recomputation.
"""

from __future__ import annotations

import hashlib
import json
import zipfile
from pathlib import Path

import numpy as np

from mavispm.core.atomic import atomic_path

__all__ = [
    "content_key",
    "is_immutable",
    "load_arrays",
    "save_arrays",
]


def content_key(*parts) -> str:
    """Hash (20 hex digits) of arrays (dtype, shape and bytes) and JSON-able values.

    Parameters
    ----------
    *parts : ndarray or JSON-able
        What the key depends on, in order.

    Returns
    -------
    str
        20 hexadecimal digits (SHA-1 prefix).
    """
    digest = hashlib.sha1()
    for part in parts:
        if isinstance(part, np.ndarray):
            digest.update(repr((part.dtype.str, part.shape)).encode())
            digest.update(np.ascontiguousarray(part).data)
        else:
            digest.update(json.dumps(part, sort_keys=True, default=str).encode())
        digest.update(b"\0")
    return digest.hexdigest()[:20]


def is_immutable(array) -> bool:
    """Whether no array can write ``array``'s memory: it ends in a read-only buffer.

    The chain of ``base`` arrays must end in an object whose buffer is read-only (a
    file mapped with ``mmap_mode="r"``); an array owning its memory, or viewing
    writable memory, can be made writable again and is not immutable. Used to decide
    whether a key of an array's content, known from where it came from (e.g.
    :attr:`~mavispm.simulate.optics.psf_grid.PSFGrid.cube_key`), still holds.
    """
    if not isinstance(array, np.ndarray) or array.flags.writeable:
        return False
    base = array
    while isinstance(base, np.ndarray):
        if base.base is None:
            return False
        base = base.base
    try:
        return memoryview(base).readonly
    except TypeError:
        return False


#: Stored members at least this large are memory-mapped by :func:`load_arrays`.
MAP_MIN_BYTES = 1 << 20


def load_arrays(path: Path) -> dict[str, np.ndarray] | None:
    """The arrays of a cache file, or None when it is missing or unreadable.

    Large members stored uncompressed (as :func:`save_arrays` writes them) are
    memory-mapped read-only instead of read through ``zipfile`` (which checks a CRC and copies every
    byte: ~1 s of CPU for the ~200 MB of stamp plans a frame loads); the others are read.

    Parameters
    ----------
    path : pathlib.Path
        An ``.npz`` cache file.

    Returns
    -------
    dict of str to ndarray, or None
    """
    try:
        with zipfile.ZipFile(path) as zf, open(path, "rb") as fh:
            out = {}
            for info in zf.infolist():
                name = info.filename.removesuffix(".npy")
                out[name] = _mapped_member(path, fh, info)
                if out[name] is None:
                    out[name] = np.lib.format.read_array(zf.open(info), allow_pickle=False)
            return out
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile):
        return None


def _mapped_member(path: Path, fh, info: zipfile.ZipInfo) -> np.ndarray | None:
    """A read-only memory map of a stored (uncompressed) ``.npy`` zip member, else None."""
    if info.compress_type != zipfile.ZIP_STORED or info.file_size < MAP_MIN_BYTES:
        return None
    fh.seek(info.header_offset)
    local = fh.read(30)  # local file header: lengths of its name and extra field at 26, 28
    if len(local) < 30 or local[:4] != b"PK\x03\x04":
        return None
    start = info.header_offset + 30 + int.from_bytes(local[26:28], "little")
    start += int.from_bytes(local[28:30], "little")
    fh.seek(start)
    version = np.lib.format.read_magic(fh)
    if version == (1, 0):
        shape, fortran, dtype = np.lib.format.read_array_header_1_0(fh)
    elif version == (2, 0):
        shape, fortran, dtype = np.lib.format.read_array_header_2_0(fh)
    else:
        return None
    if dtype.hasobject:
        raise ValueError("object arrays are not cached")
    end = fh.tell() + int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
    if end > start + info.file_size:
        raise ValueError("truncated cache member")
    if 0 in shape:
        return np.zeros(shape, dtype=dtype, order="F" if fortran else "C")
    order = "F" if fortran else "C"
    return np.memmap(path, dtype=dtype, mode="r", offset=fh.tell(), shape=shape, order=order)


def save_arrays(path: Path, arrays: dict[str, np.ndarray]) -> bool:
    """Write ``arrays`` to ``path`` atomically; False (nothing written) if the folder is not writable.

    Parameters
    ----------
    path : pathlib.Path
        The ``.npz`` cache file.
    arrays : dict of str to ndarray
        What to keep.

    Returns
    -------
    bool
        Whether the file was written.
    """
    try:
        with atomic_path(path) as tmp, open(tmp, "wb") as fh:
            np.savez(fh, **arrays)
    except OSError:
        return False
    return True
