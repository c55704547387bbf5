"""Safe names and contained paths for files mavispm writes.

User-chosen names (workflow, study, scene and epoch names) become folder names
of a work directory, and paths read from a run directory's ``summary.json``
are joined to that directory. Both must stay inside: a name is one plain path
component (:func:`check_name`), and every joined path is resolved and checked
to lie under its root (:func:`contained`).
"""

from __future__ import annotations

import os
import re
from pathlib import Path

from mavispm.core.errors import ConfigError, InputError

__all__ = [
    "NAME_PATTERN",
    "check_name",
    "contained",
]

#: Characters allowed in a name that becomes a folder or file name.
NAME_PATTERN = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.+=,-]{0,99}")


def check_name(
    name: str,
    key: str,
    source: str | None = None,
    reserved: tuple[str, ...] = (),
    what: str = "name",
) -> str:
    """Return ``name`` when it is a safe single path component, else raise.

    Parameters
    ----------
    name : str
        The name to check.
    key : str
        Dotted configuration key the name comes from (for the message).
    source : str, optional
        The configuration file.
    reserved : tuple of str
        Names that are taken (for example ``"store"`` in a work directory).
    what : str
        What the name is, for the message.

    Raises
    ------
    ConfigError
        When the name is empty, longer than 100 characters, holds a character
        outside ``A-Z a-z 0-9 _ . + = , -``, starts with ``.`` or ``-`` (hidden
        files, ``..`` and option-like names), or is reserved.
    """
    if not isinstance(name, str) or not NAME_PATTERN.fullmatch(name):
        raise ConfigError(
            f"{what} {name!r} is not a safe folder name; expected 1-100 characters from "
            "A-Z a-z 0-9 _ . + = , - not starting with '.' or '-' (no '/' or '..')",
            key=key,
            source=source,
        )
    if name in reserved:
        raise ConfigError(
            f"{what} {name!r} is reserved; choose another (reserved: {sorted(reserved)})",
            key=key,
            source=source,
        )
    return name


def contained(
    root: str | os.PathLike,
    relative: str | os.PathLike,
    what: str = "path",
    follow_links: bool = True,
) -> Path:
    """``root / relative`` resolved, which must lie inside ``root``.

    Parameters
    ----------
    root : path
        The folder the path must stay in.
    relative : path
        A path relative to ``root`` (absolute paths are refused).
    what : str
        What the path is, for the message.
    follow_links : bool
        Resolve symbolic links before the check (for paths written to). With
        False only ``..`` components are resolved, so a product that a run
        directory links into the store (``link = "symlink"``) can be read.

    Raises
    ------
    InputError
        When the path is absolute or resolves (``..``, symbolic links) outside ``root``.
    """
    root = Path(root).resolve()
    rel = Path(relative)
    if rel.is_absolute():
        raise InputError(f"{what} '{relative}' must be relative to {root}", path=root)
    target = (root / rel).resolve() if follow_links else Path(os.path.normpath(root / rel))
    if target != root and root not in target.parents:
        raise InputError(f"{what} '{relative}' leads outside {root}", path=root)
    return target
