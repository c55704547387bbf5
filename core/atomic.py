"""Atomic file output: write to a temporary file, then rename over the target.

A crash or an exception while writing never leaves a half-written file under
the final name, and never destroys an existing good file. The final file has
the permissions of any new file (``0666`` less the process umask), not the
``0600`` of a temporary file, so a work directory shared by a group (a dask
cluster's workers running as other users, with ``umask 002``) stays readable.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path

from mavispm.core.errors import InputError

__all__ = [
    "atomic_path",
    "current_umask",
]


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path in the target's folder; rename it to ``path`` on success.

    Parameters
    ----------
    path : str or os.PathLike
        The final file name. Its parent folder is created if needed.

    Yields
    ------
    pathlib.Path
        A fresh temporary file name in the same folder (same file system, so
        the final ``os.replace`` is atomic). The caller writes to it.

    Raises
    ------
    InputError
        When ``path`` is a folder or its folder cannot be created or written.

    Notes
    -----
    On any exception the temporary file is removed and the target is left
    untouched.
    """
    final = Path(path)
    if final.is_dir():
        raise InputError("is a folder; expected the name of an output file", path=final)
    try:
        final.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{final.name}.", suffix=".tmp", dir=final.parent)
    except OSError as exc:
        raise InputError(
            f"cannot write here ({exc.strerror}: '{exc.filename or final.parent}'); expected "
            "an output file name in a writable folder",
            path=final,
        ) from None
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        os.chmod(tmp_path, 0o666 & ~current_umask())
        yield tmp_path
        os.replace(tmp_path, final)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp_path.unlink()
        raise


def current_umask() -> int:
    """The process umask, read without changing it where the OS allows (Linux ``/proc``)."""
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    mask = os.umask(0o022)  # pragma: no cover - not Linux: read by setting (briefly)
    os.umask(mask)
    return mask
