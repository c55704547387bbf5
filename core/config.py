"""Configuration dataclasses built from TOML/CLI mappings with clear errors.

Stages describe their settings as frozen dataclasses (GalSim's ``GSParams`` is
the model: every knob in one documented place). :func:`from_mapping` builds one
from a plain mapping (a TOML section), rejecting unknown keys and wrong types
with a :class:`~mavispm.core.errors.ConfigError` that names the key.

A field whose ``metadata`` has ``"unit"`` holds a float in that unit; it
accepts a number (already in that unit), a string such as ``"7.5 mas"`` or an
astropy Quantity, converted to the field's unit.
"""

from __future__ import annotations

import dataclasses
import difflib
import types
import typing
from collections.abc import Iterable, Mapping
from typing import Any

import astropy.units as u

from mavispm.core.errors import ConfigError

__all__ = [
    "check_known_keys",
    "from_mapping",
    "to_mapping",
    "unit_field",
]


def unit_field(default: object, unit: str, doc: str = ""):
    """A dataclass field holding a float in ``unit`` (documented in metadata).

    Parameters
    ----------
    default : float or None
        Default value, in ``unit``.
    unit : str
        Astropy unit string; settings given as quantities ("1.5 mas") are converted to it.
    doc : str
        One-line description.

    Returns
    -------
    dataclasses.Field
    """
    return dataclasses.field(default=default, metadata={"unit": unit, "doc": doc})


def _coerce_unit(value, unit: str, key: str, source):
    try:
        if isinstance(value, u.Quantity):
            return float(value.to_value(unit))
        if isinstance(value, str):
            return float(u.Quantity(value).to_value(unit))
        if isinstance(value, bool):
            raise TypeError
        return float(value)
    except (TypeError, ValueError, u.UnitsError):
        raise ConfigError(
            f"expected a number in {unit} or a quantity string like '1 {unit}', got {value!r}",
            key=key,
            source=source,
        ) from None


def _type_name(tp) -> str:
    return getattr(tp, "__name__", str(tp))


def _coerce(value, tp, key: str, source):
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        real = [a for a in args if a is not type(None)]
        if len(real) == 1:  # Optional[X]: X's own, more precise message
            return _coerce(value, real[0], key, source)
        errors = []
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _coerce(value, arg, key, source)
            except ConfigError as exc:
                errors.append(str(exc))
        raise ConfigError(
            f"expected one of {[_type_name(a) for a in args]}, got {value!r}",
            key=key,
            source=source,
        )
    if origin is typing.Literal:
        if value not in args:
            raise ConfigError(
                f"expected one of {list(args)}, got {value!r}", key=key, source=source
            )
        return value
    if origin in (tuple, list):
        if isinstance(value, (str, bytes)) or not hasattr(value, "__iter__"):
            raise ConfigError(f"expected a list, got {value!r}", key=key, source=source)
        items = list(value)
        if origin is tuple and args and args[-1] is not Ellipsis:
            if len(items) != len(args):
                raise ConfigError(
                    f"expected {len(args)} values, got {len(items)}", key=key, source=source
                )
            out = [
                _coerce(v, a, f"{key}[{i}]", source) for i, (v, a) in enumerate(zip(items, args))
            ]
        else:
            inner = args[0] if args else Any
            out = [_coerce(v, inner, f"{key}[{i}]", source) for i, v in enumerate(items)]
        return tuple(out) if origin is tuple else out
    if origin in (dict, Mapping) or tp in (dict,):
        if not isinstance(value, Mapping):
            raise ConfigError(f"expected a table, got {value!r}", key=key, source=source)
        return dict(value)
    if tp is Any:
        return value
    if dataclasses.is_dataclass(tp):
        if isinstance(value, tp):
            return value
        if not isinstance(value, Mapping):
            raise ConfigError(
                f"expected a table of settings, got {value!r}", key=key, source=source
            )
        return from_mapping(tp, value, prefix=key, source=source)
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"expected true or false, got {value!r}", key=key, source=source)
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            if isinstance(value, float) and value.is_integer():
                return int(value)
            raise ConfigError(f"expected an integer, got {value!r}", key=key, source=source)
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"expected a number, got {value!r}", key=key, source=source)
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"expected a string, got {value!r}", key=key, source=source)
        return value
    return value


def check_known_keys(
    mapping: Mapping, allowed: Iterable[str], prefix: str = "", source: str | None = None
) -> None:
    """Raise :class:`ConfigError` for the first key of ``mapping`` not in ``allowed``.

    The message suggests the closest allowed key ("did you mean ...?") or lists them.

    Parameters
    ----------
    mapping : mapping
        Settings table.
    allowed : iterable of str
        Known keys.
    prefix : str
        Dotted prefix of the table, for messages.
    source : str, optional
        File name, for messages.
    """
    allowed = list(allowed)
    for key in mapping:
        if key not in allowed:
            close = difflib.get_close_matches(key, allowed, n=1)
            hint = f"; did you mean '{close[0]}'?" if close else f"; known keys: {sorted(allowed)}"
            raise ConfigError(f"unknown key{hint}", key=_join(prefix, key), source=source)


def from_mapping(cls, mapping: Mapping | None, prefix: str = "", source: str | None = None):
    """Build dataclass ``cls`` from ``mapping``, validating keys, types and units.

    Parameters
    ----------
    cls : type
        A dataclass type.
    mapping : mapping or None
        Settings (for example one TOML table). Missing keys take defaults.
    prefix : str
        Dotted key prefix used in error messages ("scene.optics").
    source : str, optional
        File name used in error messages.

    Raises
    ------
    ConfigError
        For unknown keys (with a suggestion), wrong types, bad units, or a
        ``__post_init__`` that rejects the values.
    """
    mapping = dict(mapping or {})
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    hints = typing.get_type_hints(cls)
    check_known_keys(mapping, fields, prefix=prefix, source=source)
    kwargs = {}
    for name, value in mapping.items():
        f = fields[name]
        full = _join(prefix, name)
        if "unit" in f.metadata and value is not None:
            kwargs[name] = _coerce_unit(value, f.metadata["unit"], full, source)
        else:
            kwargs[name] = _coerce(value, hints[name], full, source)
    try:
        return cls(**kwargs)
    except ConfigError:
        raise
    except (ValueError, TypeError) as exc:
        raise ConfigError(str(exc), key=prefix or None, source=source) from None


def to_mapping(obj: object) -> dict:
    """Plain-dict view of a settings dataclass (for provenance and hashing).

    Parameters
    ----------
    obj : dataclass instance
        Settings (nested dataclasses become nested dicts).

    Returns
    -------
    dict
    """
    return dataclasses.asdict(obj)


def _join(prefix: str, key: str) -> str:
    return f"{prefix}.{key}" if prefix else key
