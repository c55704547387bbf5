"""Run code around the first import of one module (the program's start-up loaders).

The loaders of :mod:`mavispm.core.blas_preload`, :mod:`mavispm.core.numba_start` and
:mod:`mavispm.core.table_preload` each need to act when a library module is first
executed: link a preloaded submodule, patch a method, hold modules out. One finder on
``sys.meta_path`` does that for all of them: it finds the module's spec as the import
system would, and runs ``wrap(exec_module, module)`` in place of the loader's
``exec_module(module)``; then it removes itself.
"""

from __future__ import annotations

import importlib.abc
import importlib.machinery
import sys
from collections.abc import Callable

__all__ = ["WrapOnImport", "wrap_on_import"]


class WrapOnImport(importlib.abc.MetaPathFinder):
    """Wraps the execution of module ``fullname`` when it is imported (once).

    Parameters
    ----------
    fullname : str
        The module's full name.
    wrap : callable
        ``wrap(exec_module, module)``: must call ``exec_module(module)`` once.
    """

    def __init__(self, fullname: str, wrap: Callable) -> None:
        self.fullname = fullname
        self.wrap = wrap

    def find_spec(self, fullname, path, target=None):
        """The module's spec with its loader's ``exec_module`` wrapped (only ``fullname``)."""
        if fullname != self.fullname:
            return None
        sys.meta_path.remove(self)
        spec = importlib.machinery.PathFinder.find_spec(fullname, path)
        if spec is None or spec.loader is None:
            return spec
        exec_module = spec.loader.exec_module
        spec.loader.exec_module = lambda module: self.wrap(exec_module, module)
        return spec


def wrap_on_import(fullname: str, wrap: Callable) -> bool:
    """Install a :class:`WrapOnImport` for ``fullname`` unless one is installed already.

    Parameters
    ----------
    fullname : str
        The module's full name (not yet imported).
    wrap : callable
        ``wrap(exec_module, module)``.

    Returns
    -------
    bool
        Whether it was installed here.
    """
    if any(isinstance(f, WrapOnImport) and f.fullname == fullname for f in sys.meta_path):
        return False
    sys.meta_path.insert(0, WrapOnImport(fullname, wrap))
    return True
