"""The restoration networks that can be trained: their tasks, adapters and checkpoint names."""

from __future__ import annotations

from torch import nn

__all__ = ["MODELS", "build_adapter", "checkpoint_name"]

#: model name -> task solved ("deblur": one blurry frame; "interpolation": two blurry frames).
MODELS = {"efnet": "deblur", "gem": "deblur", "refid": "interpolation"}


def build_adapter(model: str, checkpoint: str | None = None, clamp: bool = False,
                  refid_layout: tuple[int, int] = (4, 1)) -> nn.Module:
    """The adapter of ``model`` (``"efnet"``, ``"gem"`` or ``"refid"``), unclamped for training by default.

    Example:
        >>> build_adapter("refid", refid_layout=(4, 1)).net.img_chn
        12
    """
    from evlatcorr.adapters import EFNetAdapter, GEMAdapter, REFIDAdapter

    if model == "efnet":
        return EFNetAdapter(checkpoint=checkpoint, clamp=clamp)
    if model == "gem":
        return GEMAdapter(checkpoint=checkpoint, clamp=clamp)
    if model == "refid":
        m, n = refid_layout
        return REFIDAdapter(checkpoint=checkpoint, m=m, n=n, clamp=clamp)
    raise ValueError(f"unknown model {model!r}; choose from {sorted(MODELS)}")


def checkpoint_name(model: str, refid_layout: tuple[int, int] = (4, 1)) -> str:
    """The name the adapters look for with ``checkpoint="default"`` (``refid-4-1`` for REFID 4+1).

    Example:
        >>> checkpoint_name("refid", (4, 1)), checkpoint_name("refid", (11, 1)), checkpoint_name("gem")
        ('refid-4-1', 'refid', 'gem')
    """
    if model == "refid":
        m, n = refid_layout
        return "refid" if (m, n) == (11, 1) else f"refid-{m}-{n}"
    return model
