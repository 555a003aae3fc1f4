"""Input validation at the public boundary (kornia's ``KORNIA_CHECK_*`` in spirit).

Every check raises :class:`ValueError` naming the argument, what was expected and what was
received, so bad input never reaches deep inside torch.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

__all__ = [
    "check_image",
    "check_shape",
    "check_batch_vector",
    "check_finite",
    "check_exposure",
]


def check_shape(x: object, shape: Sequence[str | int], name: str) -> None:
    """Check that ``x`` is a tensor of the given symbolic shape, e.g. ``["B", "C", "H", "W"]``.

    Integers in ``shape`` must match exactly; strings match any size but must be consistent
    with each other within the call.
    """
    if not isinstance(x, Tensor):
        raise ValueError(f"{name} must be a torch.Tensor of shape {tuple(shape)}, got {type(x).__name__}")
    if x.dim() != len(shape):
        raise ValueError(f"{name} must have shape {tuple(shape)} ({len(shape)} dims), got {tuple(x.shape)}")
    seen: dict[str, int] = {}
    for dim, (want, got) in enumerate(zip(shape, x.shape)):
        if isinstance(want, int):
            if want != got:
                raise ValueError(f"{name} must have shape {tuple(shape)}, got {tuple(x.shape)} (dim {dim})")
        elif want in seen and seen[want] != got:
            raise ValueError(f"{name} must have shape {tuple(shape)}, got {tuple(x.shape)} ({want} differs)")
        else:
            seen[want] = got


def check_finite(x: Tensor, name: str) -> None:
    """Raise when ``x`` has NaN or infinite values."""
    if x.is_floating_point() and not bool(torch.isfinite(x).all()):
        bad = int((~torch.isfinite(x)).sum())
        raise ValueError(f"{name} has {bad} NaN or infinite values")


def check_image(x: object, name: str, channels: Sequence[int] = (1, 3), unit_range: bool = True) -> None:
    """Check a float image batch ``(B, C, H, W)`` with C in ``channels`` and values in [0, 1]."""
    check_shape(x, ["B", "C", "H", "W"], name)
    assert isinstance(x, Tensor)  # for the type checker; check_shape already raised otherwise
    if not x.is_floating_point():
        raise ValueError(f"{name} must be a floating point tensor, got {x.dtype}")
    if x.shape[1] not in channels:
        raise ValueError(f"{name} must have C in {tuple(channels)} channels, got {x.shape[1]}")
    check_finite(x, name)
    if unit_range and x.numel() > 0:
        lo, hi = float(x.min()), float(x.max())
        if lo < 0.0 or hi > 1.0:
            raise ValueError(f"{name} must hold linear intensities in [0, 1], got values in [{lo:.4g}, {hi:.4g}]")


def check_batch_vector(x: object, batch_size: int, name: str) -> Tensor:
    """Return ``x`` as a float64 tensor of shape ``(B,)``; scalars are broadcast."""
    if not isinstance(x, Tensor):
        x = torch.as_tensor(x, dtype=torch.float64)
    if x.dim() == 0:
        x = x.expand(batch_size)
    if x.shape != (batch_size,):
        raise ValueError(f"{name} must have shape ({batch_size},) (one value per sample), got {tuple(x.shape)}")
    check_finite(x, name)
    return x


def check_exposure(start: Tensor, end: Tensor) -> None:
    """Exposure windows must have positive length."""
    if bool((end <= start).any()):
        i = int(torch.nonzero(end <= start)[0, 0])
        raise ValueError(
            f"exposure_end must be after exposure_start; sample {i} has start {float(start[i]):.1f} us "
            f"and end {float(end[i]):.1f} us"
        )
