"""Load numba's cached kernels without first loading all of numba's compiler registries.

Before it looks in its on-disk cache, every numba dispatcher refreshes its target
context (``numba.core.caching.Cache.load_overload``): the first refresh of a process
imports and installs all of numba's typing and lowering registries (``numba.cpython.*``,
``numba.np.arraymath``, ``numba.np.random``, ``numba.typed``, ``cffi``'s C parser, ...),
~0.1 s of CPU, whatever the kernel. Those registries are only used to *compile*; a
cached kernel is machine code that needs the NRT runtime (``rtsys.initialize``) and the
C helpers that every target context installs when it is created.

:func:`load_cached_kernels_first` changes ``Cache.load_overload`` so that, until the first
refresh, it initialises the runtime and tries the cache; on a cache hit the kernel is
used as loaded, on a miss (or any error) numba's own ``load_overload`` runs (refresh,
then cache) and the compilation that follows refreshes as usual. A kernel loaded either
way is the same machine code: results are identical.

:func:`defer_numba_yaml` keeps ``numba.core.config`` from importing PyYAML (~0.01 s of
CPU) when it runs without a ``.numba_config.yaml`` to read: numba only parses that file,
which it looks for in the working directory, with PyYAML. The module then gets PyYAML on
first use (a later config reload that finds the file), so numba behaves as before.

Only the ``mavispm`` program calls them (``workflows/cli.py``: ``main()`` reading
``sys.argv``); library callers are not affected.
"""

from __future__ import annotations

import importlib
import importlib.util
import os
import sys

from mavispm.core.import_hook import wrap_on_import

__all__ = ["defer_numba_yaml", "load_cached_kernels_first"]

_PATCHED = "_mavispm_cached_first"
_REFRESHED = "_mavispm_refreshed"


def _patch(caching) -> None:
    from numba.core.runtime import nrt

    original = caching.Cache.load_overload
    if getattr(original, _PATCHED, False):
        return

    def load_overload(self, sig, target_context):
        if not getattr(target_context, _REFRESHED, False):
            try:
                nrt.rtsys.initialize(target_context)
                with self._guard_against_spurious_io_errors():
                    cres = self._load_overload(sig, target_context)
            except Exception:  # anything unusual: numba's own path below
                cres = None
            if cres is not None:
                return cres
            setattr(target_context, _REFRESHED, True)  # numba's path refreshes it
        return original(self, sig, target_context)

    load_overload.__doc__ = original.__doc__
    setattr(load_overload, _PATCHED, True)
    caching.Cache.load_overload = load_overload


def _exec_and_patch(exec_module, module) -> None:
    exec_module(module)
    _patch(module)


def load_cached_kernels_first() -> bool:
    """Have numba's cache loads skip the first registry refresh on a cache hit.

    Patches ``numba.core.caching.Cache.load_overload`` now if numba is imported, else when
    it is (numba is not imported here).

    Returns
    -------
    bool
        Whether the change was made or set up here.
    """
    caching = sys.modules.get("numba.core.caching")
    if caching is not None:
        if getattr(caching.Cache.load_overload, _PATCHED, False):
            return False
        _patch(caching)
        return True
    return wrap_on_import("numba.core.caching", _exec_and_patch)


_NUMBA_CONFIG_FILE = ".numba_config.yaml"  # numba.core.config._config_fname


class _YamlOnFirstUse:
    """Stands in for the ``yaml`` module: imports it at the first attribute looked up."""

    def __getattr__(self, name):
        return getattr(importlib.import_module("yaml"), name)


def _exec_without_yaml(exec_module, module) -> None:
    hide = "yaml" not in sys.modules and not os.path.isfile(_NUMBA_CONFIG_FILE)
    if not hide:
        exec_module(module)
        return
    have_yaml = importlib.util.find_spec("yaml") is not None
    sys.modules["yaml"] = None  # `import yaml` raises ImportError while the module runs
    try:
        exec_module(module)
    finally:
        if "yaml" in sys.modules and sys.modules["yaml"] is None:
            del sys.modules["yaml"]
    if have_yaml:  # as if imported: a config file found later is read as before
        module.yaml = _YamlOnFirstUse()
        module._HAVE_YAML = True


def defer_numba_yaml() -> bool:
    """Have ``numba.core.config`` import PyYAML only when it has a config file to read.

    Set up for the first import of ``numba.core.config`` (nothing when it is imported
    already); see the module docstring.

    Returns
    -------
    bool
        Whether it was set up here.
    """
    if "numba.core.config" in sys.modules:
        return False
    return wrap_on_import("numba.core.config", _exec_without_yaml)
