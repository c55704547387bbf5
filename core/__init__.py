"""Shared foundation: data-product formats, errors and atomic writes.

Stages exchange data only through the documented products read and written
here (see ``docs/formats.md``); no stage imports another stage's internals.
"""

from mavispm.core.atomic import atomic_path
from mavispm.core.errors import ConfigError, InputError, MavispmError
from mavispm.core.products import (
    TableSpec,
    provenance_attrs,
    read_product,
    write_product,
)

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
