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


def load_arrays(path: Path) -> dict[str, np.ndarray] | None:
    """The arrays of a cache file, or None when it is missing or unreadable.

    Parameters
    ----------
    path : pathlib.Path
        An ``.npz`` cache file.

    Returns
    -------
    dict of str to ndarray, or None
    """
    try:
        with np.load(path, allow_pickle=False) as data:
            return {name: data[name] for name in data.files}
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile):
        return None


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
