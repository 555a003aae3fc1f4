"""Package attributes imported on first use, so that importing a package runs none of its submodules."""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable, Mapping
from typing import Any

__all__ = ["lazy_attributes"]


def lazy_attributes(package: str, origins: Mapping[str, str]
                    ) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """The ``__getattr__`` and ``__dir__`` of a package whose public ``name`` lives in module ``origins[name]``.

    Example:
        >>> getattr_, dir_ = lazy_attributes("os", {"join": "os.path"})
        >>> getattr_("join")("a", "b")
        'a/b'
    """

    def __getattr__(name: str) -> Any:
        if name not in origins:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(origins[name]), name)
        setattr(sys.modules[package], name, value)  # found directly from now on
        return value

    def __dir__() -> list[str]:
        return sorted(set(origins) | set(importlib.import_module(package).__dict__))

    return __getattr__, __dir__
