"""Modules imported when first used, named at the top of the module that uses them.

A command pays at start-up only for what it runs: `labcal --help` must not import numpy, pydantic or
SQLAlchemy, though the modules that build its parser also hold the commands that need them. Such a
dependency is written once, at the module's top, beside its reason::

    if TYPE_CHECKING:
        from labcal.store import labdb
    else:
        labdb = lazy("labcal.store.labdb")  # SQLAlchemy: only a lab database needs it

and used as ``labdb.connect(...)``. The type checker reads the first branch, so every use is checked
against the real module; the import graph (import-linter's, which counts imports under
``TYPE_CHECKING``) sees the dependency; at run time the name is a stand-in that imports the module
at its first attribute access and then forwards to it.

Why not the standard library's ``importlib.util.LazyLoader`` (or the ``lazy_loader`` package, built
on it): both look the module up when the stand-in is made, which imports its parent packages
(``scipy`` for ``scipy.optimize``, ``labcal.documents`` for one of its modules) and searches
``sys.path`` once per name, at start-up, for modules the command may never use. The stand-in below
does nothing until used, and the module it imports is the ordinary one in ``sys.modules``: a test
that replaces one of its attributes is seen through the stand-in.
"""

from __future__ import annotations

import importlib
from types import ModuleType
from typing import Any


class _Deferred(ModuleType):
    """Stands for the module ``__name__`` and imports it when an attribute is first asked for."""

    def __getattr__(self, attribute: str) -> Any:
        # Called only for what the stand-in lacks: every attribute of the real module. Not copied,
        # so that an attribute replaced on the real module later is the one found.
        return getattr(importlib.import_module(self.__name__), attribute)

    def __dir__(self) -> list[str]:
        return dir(importlib.import_module(self.__name__))

    def __repr__(self) -> str:
        return f"<module {self.__name__!r}, imported when first used>"


def lazy(name: str) -> ModuleType:
    """The module ``name`` (absolute, dotted), imported at the first use of one of its attributes."""
    return _Deferred(name)
