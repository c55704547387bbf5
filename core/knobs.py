"""Accuracy and speed knobs kept apart from the model settings (GalSim's GSParams pattern).

A stage's knobs change only how well and how fast a result is computed, never what is
modelled; each stage holds them in one frozen dataclass set from the stage's ``knobs``
table (``[cluster.knobs]``, ``[scene.optics.knobs]``, ``[propermotions.knobs]``,
``[measure.knobs]``). Every knob also has a *home*: the place where it was given before the
knobs tables existed (a flat key of the stage table, or a key of a sub-table such as
``[cluster.resolution]`` or ``[scene.optics.psf]``). Both places are accepted; giving one knob
in both is an error naming it.

:func:`gather_knobs` moves knobs from their homes into the ``knobs`` table (to validate
them as one object); :func:`scatter_knobs` moves them back to their homes, the one canonical
spelling from which the workflow runner computes cache keys, so that ``[x.knobs] k = 1`` and
the home spelling of ``k = 1`` share a key (and workflows written before the knobs tables
keep theirs).

Example
-------
>>> homes = {"n_rows": ("resolution",)}
>>> gather_knobs({"resolution": {"n_rows": 64}}, homes, ("resolution",))
{'knobs': {'n_rows': 64}}
>>> scatter_knobs({"knobs": {"n_rows": 64}}, homes)
{'resolution': {'n_rows': 64}}
"""

from __future__ import annotations

import difflib
from collections.abc import Mapping

from mavispm.core.errors import ConfigError

__all__ = ["gather_knobs", "scatter_knobs"]

#: Knob name -> path of its home table inside the stage table (``()``: the stage table).
Homes = Mapping[str, tuple[str, ...]]


def _join(*parts: str) -> str:
    return ".".join(p for p in parts if p)


def _table(mapping: Mapping, key: str, prefix: str, source) -> dict:
    value = mapping.get(key)
    if value is None:
        return {}
    if not isinstance(value, Mapping):
        raise ConfigError(f"expected a table, got {value!r}", key=_join(prefix, key), source=source)
    return dict(value)


def gather_knobs(
    mapping: Mapping | None,
    homes: Homes,
    legacy_tables: tuple[str, ...] = (),
    prefix: str = "",
    source: str | None = None,
    known: tuple[str, ...] = (),
) -> dict:
    """A stage table with every knob moved from its home into the ``knobs`` table.

    Parameters
    ----------
    mapping : mapping or None
        The stage's settings table (not modified).
    homes : mapping of str to tuple of str
        Knob name to the path of its home table inside the stage table.
    legacy_tables : tuple of str
        Top-level home tables that hold nothing but knobs (``"resolution"``): removed once
        emptied; any other key left in one is an unknown key.
    prefix : str
        Dotted name of the stage table, for messages (``"cluster"``).
    source : str, optional
        File named in messages.
    known : tuple of str
        The stage table's own keys; when given, a top-level key that is none of them and
        resembles a flat knob is refused with a suggestion (``clip_iterationz``).

    Returns
    -------
    dict
        A copy with a ``knobs`` table when any knob was given (in either place).

    Raises
    ------
    ConfigError
        A knob given both in ``knobs`` and at its home, a home or ``knobs`` that is not a
        table, or an unknown key left in a legacy table; one line naming the key.
    """
    out = dict(mapping or {})
    given = "knobs" in out
    knobs = _table(out, "knobs", prefix, source)
    for name, path in homes.items():
        parent, tables = out, []
        for i, part in enumerate(path):
            table = _table(parent, part, _join(prefix, *path[:i]), source)
            tables.append((parent, part, table))
            parent = table
        if name not in parent:
            continue
        if name in knobs:
            raise ConfigError(
                f"given both here and in [{_join(prefix, 'knobs')}]; keep one",
                key=_join(prefix, *path, name),
                source=source,
            )
        knobs[name] = parent.pop(name)
        for holder, part, table in tables:  # write the copies back along the path
            holder[part] = table
        given = True
    for legacy in legacy_tables:
        if legacy not in out:
            continue
        left = _table(out, legacy, prefix, source)
        for key in left:
            close = difflib.get_close_matches(key, list(homes), n=1)
            hint = f"; did you mean '{close[0]}'?" if close else f"; known keys: {sorted(homes)}"
            raise ConfigError(f"unknown key{hint}", key=_join(prefix, legacy, key), source=source)
        del out[legacy]
    flat = [name for name, path in homes.items() if not path]
    for key in out if known else ():
        close = difflib.get_close_matches(key, flat, n=1, cutoff=0.8)
        if key not in known and close:
            raise ConfigError(
                f"unknown key; did you mean '{close[0]}'?", key=_join(prefix, key), source=source
            )
    if given:
        out["knobs"] = knobs
    return out


def scatter_knobs(mapping: Mapping | None, homes: Homes) -> dict:
    """A stage table with the ``knobs`` table's entries moved to their homes.

    The inverse of :func:`gather_knobs` for valid tables; keys of ``knobs`` that are not
    knobs stay in it (validation names them), and a knob given in both places keeps both
    (validation refuses it).

    Parameters
    ----------
    mapping : mapping or None
        The stage's settings table (not modified).
    homes : mapping of str to tuple of str
        Knob name to the path of its home table inside the stage table.

    Returns
    -------
    dict
        A copy without a ``knobs`` table when all its entries found their homes.
    """
    out = dict(mapping or {})
    if not isinstance(out.get("knobs"), Mapping):
        return out
    knobs = dict(out.pop("knobs"))
    for name, path in homes.items():
        if name not in knobs:
            continue
        parent = out
        for part in path:
            child = parent.get(part)
            if child is not None and not isinstance(child, Mapping):
                break
            parent[part] = dict(child or {})
            parent = parent[part]
        else:
            if name not in parent:
                parent[name] = knobs.pop(name)
    if knobs:
        out["knobs"] = knobs
    return out
