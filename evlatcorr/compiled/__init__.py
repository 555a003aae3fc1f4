"""What the compiled CPU passes share: numba, imported and compiled on first use, and threads that split the work.

The passes (:mod:`~evlatcorr.compiled.event_runs`, :mod:`~evlatcorr.compiled.window_reads`,
:mod:`~evlatcorr.compiled.high_pass`, :mod:`~evlatcorr.compiled.gradients`) walk each pixel's events, or each image's
pixels, in a loop, which eager PyTorch can only do as a dozen passes over event-, table- or image-sized tensors. They
are compiled with numba on first use (a few seconds, then loaded from numba's cache beside this package) and run in
``torch.get_num_threads()`` Python threads: the compiled code releases the GIL, and plain threads need no OpenMP
runtime beside PyTorch's (numba's own parallel loops take one, which a process that forks afterwards, as a DataLoader
does, cannot use safely). A GPU keeps eager PyTorch's way, where launches, not memory traffic, bound the search.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable

import torch

__all__ = ["ENABLED", "check_arrays", "in_threads", "jit", "workers_for"]

# Whether a CPU takes the compiled passes; ``EVLATCORR_COMPILED=0`` (or False here) takes eager PyTorch's way
# everywhere, e.g. to compare the two
ENABLED = os.environ.get("EVLATCORR_COMPILED", "1") != "0"


def jit(function: Callable) -> Callable:
    """``function`` compiled by numba (no GIL held, cached on disk, numpy's division semantics)."""
    import numba

    return numba.njit(nogil=True, cache=True, error_model="numpy")(function)


def in_threads(kernel: Callable, workers: int, *args) -> None:
    """Run ``kernel(i, workers, *args)`` for ``i`` in ``range(workers)``, each in its own thread (the first in this
    one); each call must write its own part of the outputs."""
    threads = [threading.Thread(target=kernel, args=(i, workers, *args)) for i in range(1, workers)]
    for thread in threads:
        thread.start()
    try:
        kernel(0, workers, *args)
    finally:
        for thread in threads:
            thread.join()


def workers_for(items: int, per_worker: int = 1) -> int:
    """How many threads share ``items`` (at least ``per_worker`` each): at most ``torch.get_num_threads()``."""
    return max(1, min(torch.get_num_threads(), items // max(1, per_worker)))


def check_arrays(arrays: dict[str, torch.Tensor], dims: int, dtypes: tuple[torch.dtype, ...] | None = None) -> None:
    """Refuse what a compiled pass cannot read safely (it checks no index): each of ``arrays`` (by name) must be a
    contiguous CPU tensor of ``dims`` dimensions (and one of ``dtypes``, if given).

    Raises:
        ValueError: naming the first array that is not.
    """
    for name, array in arrays.items():
        if not isinstance(array, torch.Tensor) or array.device.type != "cpu" or array.dim() != dims:
            got = f"{array.dim()}-D on {array.device}" if isinstance(array, torch.Tensor) else type(array).__name__
            raise ValueError(f"{name} must be a {dims}-D CPU tensor, got {got}")
        if not array.is_contiguous():
            raise ValueError(f"{name} must be contiguous")
        if dtypes is not None and array.dtype not in dtypes:
            raise ValueError(f"{name} must be one of {[str(d) for d in dtypes]}, got {array.dtype}")
