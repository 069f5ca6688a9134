"""Names of a package imported from their modules on first use (PEP 562)."""

from __future__ import annotations

import importlib
from typing import Callable, Mapping


def lazy_names(package: str, namespace: dict, table: Mapping[str, tuple[str, ...]]) -> tuple[Callable, Callable]:
    """``(__getattr__, __dir__)`` for ``package`` whose ``namespace`` (its ``globals()``) gets each
    name of ``table`` (relative module -> names) from that module on first use, then keeps it."""
    module_of = {name: module for module, names in table.items() for name in names}

    def __getattr__(name):
        module = module_of.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(module, package), name)
        namespace[name] = value
        return value

    def __dir__():
        return sorted(set(namespace) | set(module_of))

    return __getattr__, __dir__
