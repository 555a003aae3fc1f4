"""The parts every adapter shares: input checks, event choice, padding, output finishing, weights and repr.

:class:`NetworkAdapter` is the base class of the adapters (EDI, EFNet, GEM, REFID). A subclass keeps only
what is its own: the event representation it builds, the network it runs and a short ``forward`` that
strings these steps together::

    self.check_frames(frames)                      # an EventFrames batch with a valid blurry frame
    events = self.input_events(frames)             # frames.corrected when set, else frames.events
    ph, pw = self.padding(height, width, divisor)  # or the ValueError naming pad=True
    x, voxel = self.pad_inputs((ph, pw), rgb(image), voxel)
    out = self.finish(self.net(x, voxel), frames)  # crop, clamp, grey, dtype and device of blurry
"""

from __future__ import annotations

from typing import ClassVar

import torch.nn.functional as F
from torch import Tensor, nn

from evlatcorr.checks import check_image
from evlatcorr.events import Events
from evlatcorr.frames import EventFrames

__all__ = ["NetworkAdapter", "rgb"]


def rgb(image: Tensor) -> Tensor:
    """A grey image batch repeated to three channels (a view); a colour one as it is.

    Args:
        image: :math:`(B, C, H, W)` with C = 1 or 3.

    Returns:
        :math:`(B, 3, H, W)`.

    Example:
        >>> import torch
        >>> rgb(torch.zeros(2, 1, 4, 5)).shape
        torch.Size([2, 3, 4, 5])
    """
    return image.expand(-1, 3, -1, -1) if image.shape[1] == 1 else image


class NetworkAdapter(nn.Module):
    """Base class of the adapters that run a restoration model on an :class:`~evlatcorr.frames.EventFrames` batch.

    Subclasses set ``model_name`` (used in error messages) and register their network as ``self.net`` (a model
    without weights, such as EDI, has none); those that call :meth:`padding` set ``self.pad`` and those that
    call :meth:`finish` set ``self.clamp`` (the constructor arguments of the same names).

    Attributes:
        model_name: the model's name in messages, e.g. ``"EFNet"``.
        mean_before_clamp: :meth:`finish` takes the grey channel mean before clamping (EFNet) rather than
            after it (GEM, REFID); the two differ where a channel is outside [0, 1].
        short_repr: ``repr`` shows the adapter's settings and the network's one-line summary instead of
            every layer.
    """

    model_name: ClassVar[str] = "model"
    mean_before_clamp: ClassVar[bool] = False
    short_repr: ClassVar[bool] = True

    def check_frames(self, frames: object, image: bool = True) -> None:
        """Refuse anything but an :class:`~evlatcorr.frames.EventFrames` batch.

        Args:
            frames: the adapter's input.
            image: also check ``frames.blurry``: a float :math:`(B, C, H, W)` batch, C = 1 or 3, in [0, 1].

        Raises:
            ValueError: naming the adapter and the type it got, or what is wrong with ``frames.blurry``.
        """
        if not isinstance(frames, EventFrames):
            raise ValueError(f"{type(self).__name__} takes an EventFrames batch, got {type(frames).__name__}")
        if image:
            check_image(frames.blurry, "frames.blurry")

    @staticmethod
    def input_events(frames: EventFrames) -> Events:
        """The events the model reads: ``frames.corrected`` when a corrector filled it, else ``frames.events``."""
        return frames.corrected if frames.corrected is not None else frames.events

    def padding(self, height: int, width: int, divisor: int) -> tuple[int, int]:
        """Rows and columns to add at the bottom and right so that H and W are multiples of ``divisor``.

        Args:
            height: image height H.
            width: image width W.
            divisor: the network's size granularity.

        Returns:
            ``(ph, pw)``, each in ``[0, divisor)``; ``(0, 0)`` when H and W are multiples already.

        Raises:
            ValueError: when padding is needed but the adapter was built with ``pad=False``, naming the model,
                the sizes and ``pad=True``.

        Example:
            >>> adapter = NetworkAdapter()
            >>> adapter.pad = True
            >>> adapter.padding(30, 37, 8)
            (2, 3)
        """
        ph, pw = (-height) % divisor, (-width) % divisor
        if (ph or pw) and not self.pad:
            raise ValueError(f"{self.model_name} needs H and W to be multiples of {divisor}, got (H, W)=({height}, "
                             f"{width}); crop the frames or use {type(self).__name__}(pad=True)")
        return ph, pw

    @staticmethod
    def pad_inputs(padding: tuple[int, int], image: Tensor, *maps: Tensor | None,
                   scale: int = 1) -> tuple[Tensor | None, ...]:
        """Pad the network's inputs at the bottom and right: the image by replication, event maps with zeros.

        Args:
            padding: ``(ph, pw)`` rows and columns to add to the image (:meth:`padding`).
            image: :math:`(..., H, W)`, replicate-padded to :math:`(..., H + ph, W + pw)`.
            *maps: event tensors :math:`(..., h, w)` (``None`` passes through), zero-padded to
                :math:`((H + ph) // scale, (W + pw) // scale)`.
            scale: image-to-event-map resolution ratio.

        Returns:
            the padded image, then the padded maps in order; the inputs themselves when ``padding`` is (0, 0).

        Example:
            >>> import torch
            >>> x, e = NetworkAdapter.pad_inputs((1, 0), torch.ones(1, 3, 2, 4), torch.ones(1, 6, 2, 4))
            >>> x[0, 0, :, 0].tolist(), e[0, 0, :, 0].tolist()
            ([1.0, 1.0, 1.0], [1.0, 1.0, 0.0])
        """
        ph, pw = padding
        if not (ph or pw):
            return (image, *maps)
        height, width = (image.shape[-2] + ph) // scale, (image.shape[-1] + pw) // scale
        padded = [None if m is None else F.pad(m, (0, width - m.shape[-1], 0, height - m.shape[-2])) for m in maps]
        return (F.pad(image, (0, pw, 0, ph), mode="replicate"), *padded)

    def finish(self, out: Tensor, frames: EventFrames) -> Tensor:
        """The network's RGB output as the adapter's ``output``.

        Crops the padding off (to ``frames.sensor_size``), clamps to [0, 1] when ``self.clamp``, takes the
        channel mean for grey frames (before the clamp when ``mean_before_clamp``) and casts to the dtype and
        device of ``frames.blurry``.

        Args:
            out: :math:`(B, 3, H', W')` or :math:`(B, T, 3, H', W')`, with ``H' >= H`` and ``W' >= W``.
            frames: the input batch.

        Returns:
            :math:`(B, C, H, W)` or :math:`(B, T, C, H, W)`, C of ``frames.blurry``.
        """
        height, width = frames.sensor_size
        out = out[..., :height, :width]
        grey = frames.blurry.shape[1] == 1
        if grey and self.mean_before_clamp:
            out = out.mean(dim=-3, keepdim=True)
        if self.clamp:
            out = out.clamp(0.0, 1.0)
        if grey and not self.mean_before_clamp:
            out = out.mean(dim=-3, keepdim=True)
        return out.to(device=frames.blurry.device, dtype=frames.blurry.dtype)

    def load_checkpoint(self, checkpoint: str | None, name: str) -> None:
        """Load ``checkpoint`` into ``self.net`` (strict), or keep the random weights for ``None``.

        Args:
            checkpoint: ``None``, ``"default"`` (shipped ``checkpoints/<name>*.safetensors``) or a path, see
                :func:`~evlatcorr.adapters.checkpoint.resolve_checkpoint`.
            name: the model's checkpoint name, e.g. ``"efnet"`` or ``"refid-4-1"``.

        Raises:
            FileNotFoundError: when the file or the default checkpoint does not exist.
            ValueError: when the weights cannot be read or do not match the network.
        """
        from evlatcorr.adapters.checkpoint import load_weights, resolve_checkpoint

        path = resolve_checkpoint(checkpoint, name)
        if path is not None:
            load_weights(self.net, path, strict=True)

    def __repr__(self) -> str:
        net = getattr(self, "net", None)  # a registered submodule; adapters without weights have none
        if net is None or not self.short_repr:
            return super().__repr__()
        # nn.Module's repr would list every layer of the network
        return f"{type(self).__name__}(\n  {self.extra_repr()}\n  (net): {type(net).__name__}({net.extra_repr()})\n)"
