"""CPU memory and thread settings asked for by our entry points (importing the package sets nothing).

EDI and the latency search stream through tensors of tens to hundreds of MB, and on a CPU the page faults of
touching fresh memory can cost more than the arithmetic:

- :func:`prefer_large_pages`: PyTorch backs large CPU tensors with 2 MB pages when ``THP_MEM_ALLOC_ENABLE=1``
  is in the environment at its first allocation (EDI was 2.5x slower on 4 KB pages), which importing kornia,
  lightning or torchmetrics already makes: so an entry point asks for it before importing them.
- :func:`keep_freed_memory`: glibc's malloc maps each block of more than a few MB afresh and unmaps it when it
  is freed, so every new tensor of that size pays its page faults again; it is asked to keep freed memory for
  the next tensor instead.

- :func:`prefer_short_spin`: after each parallel operation PyTorch's OpenMP threads spin for a while before they
  sleep, and on a CPU with few cores they then share those cores with the compiled passes' threads
  (:mod:`evlatcorr.compiled`) that run next: a short spin (``GOMP_SPINCOUNT``) keeps the cores for them.

:func:`prefer_fast_memory` asks for all three.
"""

from __future__ import annotations

import ctypes
import os

__all__ = ["prefer_large_pages", "keep_freed_memory", "prefer_short_spin", "prefer_fast_memory"]

VARIABLE = "THP_MEM_ALLOC_ENABLE"
SPIN_VARIABLE = "GOMP_SPINCOUNT"
# GNU OpenMP's spins before an idle thread sleeps (its default: 300000): on this project's 2-core CPU the default
# search took 110 ms with 3000 against 154 ms with the default (`python benchmarks/speed.py --part stages`), and EFNet's
# forward pass the same 1.04 s either way (`--part adapters`)
SHORT_SPIN = "3000"
KEEP_VARIABLE = "EVLATCORR_KEEP_FREED_MEMORY"
# glibc's mallopt parameters, and the threshold both are set to (the largest C int: 2 GiB)
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
_THRESHOLD_BYTES = 2**31 - 1


def prefer_large_pages() -> bool:
    """Set ``THP_MEM_ALLOC_ENABLE=1`` unless the environment already says (``=0`` opts out).

    Only takes effect when called before the process's first tensor (before importing kornia, lightning,
    torchmetrics or most of :mod:`evlatcorr`); ``import evlatcorr`` itself makes none.

    Returns:
        whether large pages are asked for.

    Example:
        >>> import os
        >>> prefer_large_pages() == (os.environ["THP_MEM_ALLOC_ENABLE"] == "1")
        True
    """
    return os.environ.setdefault(VARIABLE, "1") == "1"


def keep_freed_memory() -> bool:
    """Have glibc's malloc keep freed memory for the next allocation instead of handing large blocks back.

    Sets ``M_MMAP_THRESHOLD`` and ``M_TRIM_THRESHOLD`` (``mallopt``) to 2 GiB: blocks below that come from the
    heap, and freed ones stay there, already touched. On this project's 2-core CPU the default latency search
    took 298-306 ms with it and 310-397 ms without (``python benchmarks/speed.py --part stages``, three runs each,
    ``EVLATCORR_KEEP_FREED_MEMORY=0`` for the second). The price: the process's resident memory stays near its
    peak instead of shrinking after it. Affects the allocations after the call (call it any time).
    ``EVLATCORR_KEEP_FREED_MEMORY=0`` opts out.

    Returns:
        whether the setting was applied (False when opted out, or without glibc's ``mallopt``).

    Example:
        >>> keep_freed_memory() in (True, False)
        True
    """
    if os.environ.get(KEEP_VARIABLE, "1") == "0":
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError, TypeError):  # not glibc (or no C library to load by name)
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    return bool(mallopt(_M_MMAP_THRESHOLD, _THRESHOLD_BYTES)) and bool(mallopt(_M_TRIM_THRESHOLD, _THRESHOLD_BYTES))


def prefer_short_spin() -> bool:
    """Set ``GOMP_SPINCOUNT=3000`` unless the environment already says: PyTorch's idle OpenMP threads then sleep after
    a few microseconds rather than spin for about a millisecond, and leave the cores to the compiled passes.

    Only takes effect when called before torch is imported (GNU OpenMP reads it as it loads); ``import evlatcorr``
    itself imports no torch. Set ``GOMP_SPINCOUNT`` yourself to keep another value.

    Returns:
        whether the short spin is what the environment now says.

    Example:
        >>> prefer_short_spin() == (os.environ["GOMP_SPINCOUNT"] == "3000")
        True
    """
    return os.environ.setdefault(SPIN_VARIABLE, SHORT_SPIN) == SHORT_SPIN


def prefer_fast_memory() -> tuple[bool, bool]:
    """:func:`prefer_large_pages`, :func:`keep_freed_memory` and :func:`prefer_short_spin`: what our command lines and
    scripts ask for first, before torch is imported.

    Returns:
        whether large pages and kept memory were asked for.
    """
    prefer_short_spin()
    return prefer_large_pages(), keep_freed_memory()
