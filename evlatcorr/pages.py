"""Large memory pages for PyTorch's CPU tensors, asked for by our entry points (importing the package does not).

EDI and the latency search stream through tensors of hundreds of MB; on the CPU, touching them on 4 KB pages
costs more page-fault time than arithmetic (EDI 2.5x slower). PyTorch backs large CPU tensors with 2 MB pages
when ``THP_MEM_ALLOC_ENABLE=1`` is in the environment at its first allocation, which importing kornia,
lightning or torchmetrics already makes: so an entry point asks for it before importing them.
"""

from __future__ import annotations

import os

__all__ = ["prefer_large_pages"]

VARIABLE = "THP_MEM_ALLOC_ENABLE"


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
