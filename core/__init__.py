"""Shared foundation: data-product formats, errors and atomic writes.

Stages exchange data only through the documented products read and written
here (see ``docs/formats.md``); no stage imports another stage's internals.
"""

from mavispm.core.errors import ConfigError, InputError, MavispmError

#: Public name -> module that defines it, imported on first use (:func:`__getattr__`):
#: ``mavispm.core.products`` imports astropy.units, astropy.table and h5py (~0.3 s of
#: CPU), which importing ``mavispm.core.errors`` (the CLI does) should not.
_LAZY = {
    "TableSpec": "mavispm.core.products",
    "atomic_path": "mavispm.core.atomic",
    "provenance_attrs": "mavispm.core.products",
    "read_product": "mavispm.core.products",
    "write_product": "mavispm.core.products",
}

__all__ = [
    "ConfigError",
    "InputError",
    "MavispmError",
    "TableSpec",
    "atomic_path",
    "provenance_attrs",
    "read_product",
    "write_product",
]


def __getattr__(name: str):
    """Import a public name's module on first use."""
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'mavispm.core' has no attribute {name!r}")
    import importlib

    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))
