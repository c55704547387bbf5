"""Import ``astropy.table`` without its file-format connectors (program start-up).

``astropy.table``'s ``__init__`` ends by importing the modules that connect
``Table.read`` / ``Table.write`` to file formats: ``astropy.io.ascii`` (all its readers,
``yaml``), ``astropy.io.fits``, ``astropy.io.votable``, ``astropy.io.misc`` (HDF5,
parquet, pandas): ~0.08 s of user CPU of every ``mavispm`` process (measured: ``import
astropy.table`` 0.44 s against 0.36 s without them), which most commands never use
(mavispm's products are read and written with h5py).

:func:`import_table_without_connectors` has ``astropy.table``, when it is imported,
hold those five modules out, then import them on first use: the first call of a method of
astropy's I/O registry (``Table.read``, ``Table.write``, ``get_formats``, ...) imports
them all, exactly as ``astropy.table`` would have, and carries on. Importing one of them
(or ``astropy.io.ascii``, which imports its own) also works as usual.

Only the ``mavispm`` program calls it (``workflows/cli.py``: ``main()`` reading
``sys.argv``), before the command's modules are imported; library callers are not
affected.
"""

from __future__ import annotations

import importlib
import sys
import types

from mavispm.core.import_hook import wrap_on_import

__all__ = ["CONNECTORS", "import_table_without_connectors", "load_connectors"]

#: The connector modules ``astropy.table/__init__.py`` imports (astropy 5.x - 8.x).
CONNECTORS = (
    "astropy.io.ascii.connect",
    "astropy.io.fits.connect",
    "astropy.io.misc.connect",
    "astropy.io.misc.pandas.connect",
    "astropy.io.votable.connect",
)

#: The registry methods that need the formats: shadowed until the first call.
_REGISTRY_METHODS = (
    "read",
    "write",
    "get_reader",
    "get_writer",
    "get_formats",
    "identify_format",
)


def load_connectors() -> None:
    """Import the connector modules now and drop the registry's placeholders (idempotent)."""
    from astropy.io.registry import compat

    registry = compat.default_registry
    for name in _REGISTRY_METHODS:
        registry.__dict__.pop(name, None)
    for name in CONNECTORS:
        importlib.import_module(name)


def _deferred(name: str):
    def method(*args, **kwargs):
        load_connectors()
        from astropy.io.registry import compat

        return getattr(compat.default_registry, name)(*args, **kwargs)

    method.__name__ = name
    return method


def _exec_deferring(exec_module, module) -> None:
    """Run ``astropy.table``'s code with the connectors held out, then shadow the registry."""
    if any(n in sys.modules for n in CONNECTORS):  # one came in meanwhile: as usual
        exec_module(module)
        return
    placeholders = {n: types.ModuleType(n) for n in CONNECTORS}
    sys.modules.update(placeholders)
    try:
        exec_module(module)
    finally:
        for name, placeholder in placeholders.items():
            if sys.modules.get(name) is placeholder:
                del sys.modules[name]
    from astropy.io.registry import compat

    for name in _REGISTRY_METHODS:
        setattr(compat.default_registry, name, _deferred(name))


def import_table_without_connectors() -> bool:
    """Have ``astropy.table``, when imported, defer its format connectors to their first use.

    Does nothing when ``astropy.table`` or one of the connectors is already imported.

    Returns
    -------
    bool
        Whether the deferral was set up here.
    """
    if "astropy.table" in sys.modules or any(n in sys.modules for n in CONNECTORS):
        return False
    return wrap_on_import("astropy.table", _exec_deferring)
