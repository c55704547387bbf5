"""Warnings raised while a node runs are kept in its record, not printed over the bars.

Libraries the stages call (dynesty, photutils, numpy, astropy) warn through
:mod:`warnings`. While a node runs on a thread, :func:`capture` routes every
warning that thread shows into the node's list (deduplicated, in order); the
runner stores the list in the node's completion record, the run summary and the
report. Warnings of threads that run no node are shown as usual. The routing is
per thread, so nodes running side by side on a thread pool keep their own lists
(``warnings.catch_warnings`` is process-global and cannot do this).
"""

from __future__ import annotations

import contextlib
import threading
import warnings
from pathlib import Path

__all__ = ["capture", "format_warning", "install"]

_STATE = threading.local()
_ORIGINAL = warnings.showwarning


def format_warning(message: Warning | str, category: type, filename: str, lineno: int) -> str:
    """One line: ``Category: message (file.py:line)``.

    Parameters
    ----------
    message : Warning or str
    category : type
    filename : str
    lineno : int

    Returns
    -------
    str
    """
    text = " ".join(str(message).split())
    return f"{category.__name__}: {text} ({Path(filename).name}:{lineno})"


def _showwarning(message, category, filename, lineno, file=None, line=None):
    sink = getattr(_STATE, "sink", None)
    if sink is None:
        return _ORIGINAL(message, category, filename, lineno, file, line)
    text = format_warning(message, category, filename, lineno)
    if text not in sink:
        sink.append(text)
    return None


def install() -> None:
    """Route shown warnings through the per-thread sink (idempotent, process-wide)."""
    if warnings.showwarning is not _showwarning:
        warnings.showwarning = _showwarning


@contextlib.contextmanager
def capture():
    """Collect the warnings this thread shows inside the block.

    Yields
    ------
    list of str
        The warnings, one line each (:func:`format_warning`), filled as they come.
    """
    install()
    previous = getattr(_STATE, "sink", None)
    sink: list[str] = []
    _STATE.sink = sink
    try:
        yield sink
    finally:
        _STATE.sink = previous
