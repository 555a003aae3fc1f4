"""Package attributes imported on first use, so that importing a package runs none of its submodules."""

from __future__ import annotations

import importlib
import importlib.util
import sys
from collections.abc import Callable, Mapping
from typing import Any

__all__ = ["lazy_attributes"]


def lazy_attributes(package: str, origins: Mapping[str, str]
                    ) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """The ``__getattr__`` and ``__dir__`` of a package whose public ``name`` lives in module ``origins[name]``.

    A submodule is found by attribute too (``evlatcorr.edi`` after ``import evlatcorr``), as if the package had
    imported it.

    Example:
        >>> getattr_, dir_ = lazy_attributes("evlatcorr", {"Events": "evlatcorr.events"})
        >>> getattr_("Events").__name__, getattr_("edi").__name__
        ('Events', 'evlatcorr.edi')
    """

    def __getattr__(name: str) -> Any:
        if name in origins:
            value = getattr(importlib.import_module(origins[name]), name)
            setattr(sys.modules[package], name, value)  # found directly from now on
            return value
        if not name.startswith("__") and importlib.util.find_spec(f"{package}.{name}") is not None:
            return importlib.import_module(f"{package}.{name}")  # which sets the package's attribute
        raise AttributeError(f"module {package!r} has no attribute {name!r}")

    def __dir__() -> list[str]:
        return sorted(set(origins) | set(importlib.import_module(package).__dict__))

    return __getattr__, __dir__
