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

Only the ``mavispm`` program calls it (``workflows/cli.py``: ``main()`` reading
``sys.argv``); library callers are not affected.
"""

from __future__ import annotations

import sys

from mavispm.core.import_hook import wrap_on_import

__all__ = ["load_cached_kernels_first"]

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
