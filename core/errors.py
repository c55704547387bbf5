"""Exceptions that carry a clear, user-facing message.

Every error raised for bad input names the file, column or parameter and what
was expected. The CLI prints these messages without a traceback.
"""

from __future__ import annotations

__all__ = [
    "ConfigError",
    "InputError",
    "MavispmError",
]


class MavispmError(Exception):
    """Base class for all errors mavispm reports to its users."""


class InputError(MavispmError, ValueError):
    """Bad input data: a file, column or value that is not what was expected.

    Parameters
    ----------
    message : str
        What is wrong and what was expected.
    path : str or os.PathLike, optional
        The file concerned; prefixed to the message.
    column : str, optional
        The column or dataset concerned; prefixed to the message.
    """

    def __init__(self, message: str, path=None, column: str | None = None):
        where = []
        if path is not None:
            where.append(f"file '{path}'")
        if column is not None:
            where.append(f"column '{column}'")
        prefix = (", ".join(where) + ": ") if where else ""
        super().__init__(prefix + message)
        self.path = path
        self.column = column


class ConfigError(MavispmError, ValueError):
    """Bad configuration: an unknown key, a wrong type or an impossible value.

    Parameters
    ----------
    message : str
        What is wrong and what was expected.
    key : str, optional
        Dotted name of the configuration key concerned.
    source : str, optional
        The configuration file concerned.
    """

    def __init__(self, message: str, key: str | None = None, source=None):
        where = []
        if source is not None:
            where.append(f"file '{source}'")
        if key is not None:
            where.append(f"key '{key}'")
        prefix = (", ".join(where) + ": ") if where else ""
        super().__init__(prefix + message)
        self.key = key
        self.source = source
