"""REFID (Sun et al., CVPR 2023, "Event-Based Frame Interpolation with Ad-hoc Deblurring") as an adapter.

A re-implementation of the official network (``FinalBidirectionAttenfusion`` in AHupuJR/REFID,
``basicsr/models/archs/XXNet_final_attenfusion_arch.py``, commit f94eb19) whose ``state_dict`` has the
official key names and shapes, so the released BasicSR ``.pth`` weights load with ``strict=True`` and give
the official outputs number for number (see ``tests/test_adapters_refid.py``), plus the official event
representation and input layout.

Official data layout (``basicsr/data/image_npy_dataset.py``, ``GoProEventRecurrentDataset``), for ``m``
sharp frames per blurry frame and ``n`` skipped sharp frames between two blurry frames (11 and 1 for the
released "11+1" weights): sharp frames ``τ_0 .. τ_{2m+n-1}`` at a spacing ``δ``; the left blurry frame
averages ``τ_0 .. τ_{m-1}``, the right one ``τ_{m+n} .. τ_{2m+n-1}``. The events are those of the
``2m+n+1`` inter-frame intervals from ``τ_{-1}`` to ``τ_{2m+n}`` (one interval before the left exposure
and one after the right one), turned into **one** voxel grid of ``num_bins = 2m+n+1`` bins
(:func:`refid_voxel_grid`). The network sees

* ``event`` :math:`(B, 2m+n, 2, H, W)`: the overlapping bin pairs ``voxel[i:i+2]``, ``i = 0 .. 2m+n-1``;
* ``x`` :math:`(B, 2m+4, H, W)` = ``cat(left RGB, voxel[1:m], right RGB, voxel[m+n+2:])``: 26 channels
  for 11+1. (The right slice starts one bin later than the mirror image of the left one, ``1:m``; an
  official quirk kept as is.)

and returns ``2m+n`` frames: output ``k`` is the sharp frame ``τ_k`` (``0 .. m-1`` inside the left
exposure, ``m .. m+n-1`` between the exposures, the rest inside the right exposure); the official test
computes its deblurring metrics on the first and last ``m`` and its interpolation metrics on the middle
``n``, after clamping to [0, 1].

Mapping to :class:`~evlatcorr.frames.EventFrames` (:func:`refid_window`): the exposures are taken as
time intervals the blurry frames integrate over, with the sharp frames at the centres of ``m`` equal
sub-intervals (``frame_offset=0.5``: ``τ_0 = exposure_start + δ/2``), and the whole span from the left
exposure start to the right exposure end split uniformly: ``δ = (end_right - start_left) / (2m+n)``. The
voxel window is then ``[start_left - δ/2, end_right + δ/2)`` and output ``k`` is at
``start_left + (k + 1/2) δ``. ``frame_offset=0`` is the convention of the HighREV reader
(``exposure_start``/``end`` are the first and last sharp-frame times). The layout assumes the gap between
the exposures is ``n`` sharp-frame intervals (``n ≈ m · gap / exposure``); other duty cycles are mapped
with the same uniform spacing (the frame at the middle of the gap stays exactly the middle output).

Single-frame deblurring (``mode="deblur"``): the official repository does it with the same network class
and a different layout (``basicsr/data/Deblur_image_npy_dataset.py``): one blurry frame, the ``m+1``
intervals from ``τ_{-1}`` to ``τ_m`` in one voxel grid of ``m+1`` bins, ``event`` = its ``m`` bin pairs,
``x = cat(RGB, voxel[1:-1])`` (``m+2`` = 13 channels), and ``m`` output frames across the exposure.
This needs weights trained that way (``img_chn=13``); the 11+1 interpolation weights do not load into it.
Deblurring with the interpolation weights is done as the official test does: run ``"interpolation"`` on a
pair and take the output nearest mid-exposure (output ``(m-1)/2``).

Official quirks reproduced (see ``/work/shared/specs/refid_state_dict.json``): all forward frames receive
the backward recurrent states of frame 0 (list aliasing in the official loop); a double LeakyReLU(0.2) in
the event encoders not using attention fusion; the attention fusion's channel attention ``se_1`` used for
both modalities (``se_2`` unused) and its encoder's ``conv`` unused; no output activation. The voxel grid
is not normalised (the official normalisation is a no-op) and its timestamps are mapped by the first and
last event of the window, not by the window's bounds (``normalize="events"``). Not reproduced: the
official loader casts absolute timestamps to float32 before mapping them (lossy for large µs values);
here they are mapped in float64 relative to the window, then the grid is cast to float32.
"""

from __future__ import annotations

import math
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from evlatcorr.adapters.base import NetworkAdapter, rgb
from evlatcorr.checks import check_int
from evlatcorr.events import Events
from evlatcorr.frames import EventFrames

__all__ = [
    "REFIDAdapter",
    "REFIDNet",
    "nearest_frames",
    "refid_inputs",
    "refid_output_times",
    "refid_voxel_grid",
    "refid_window",
]

NUM_PARAMETERS_11_1 = 15_928_355  # official FinalBidirectionAttenfusion, img_chn=26 (11+1 and 11+3)
_MODES = ("interpolation", "deblur")
_NORMALIZE = ("events", "window")


# --------------------------------------------------------------------------------------------------
# network
# --------------------------------------------------------------------------------------------------
class _ConvAct(nn.Module):
    """``conv2d`` followed by a LeakyReLU (``slope=None``: no activation)."""

    def __init__(self, cin: int, cout: int, kernel: int, padding: int, slope: float | None) -> None:
        super().__init__()
        self.conv2d = nn.Conv2d(cin, cout, kernel, 1, padding)
        self.slope = slope

    def forward(self, x: Tensor) -> Tensor:
        x = self.conv2d(x)
        return x if self.slope is None else F.leaky_relu(x, self.slope)


class _ResBlockNoBN(nn.Module):
    """``x + conv2(relu(conv1(x)))``; weights initialised as BasicSR does (Kaiming normal × 0.1, zero bias)."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(channels, channels, 3, 1, 1)
        self.conv2 = nn.Conv2d(channels, channels, 3, 1, 1)
        with torch.no_grad():
            for conv in (self.conv1, self.conv2):
                nn.init.kaiming_normal_(conv.weight)
                conv.weight.mul_(0.1)
                conv.bias.zero_()

    def forward(self, x: Tensor) -> Tensor:
        return x + self.conv2(F.relu(self.conv1(x)))


class _ConvResTrunk(nn.Module):
    """``main``: conv3x3 (cin -> cout) + LeakyReLU(0.1), then ``num_block`` residual blocks."""

    def __init__(self, cin: int, cout: int, num_block: int) -> None:
        super().__init__()
        self.main = nn.Sequential(nn.Conv2d(cin, cout, 3, 1, 1), nn.LeakyReLU(0.1),
                                  nn.Sequential(*[_ResBlockNoBN(cout) for _ in range(num_block)]))

    def forward(self, x: Tensor) -> Tensor:
        return self.main(x)


class _RecurrentCell(nn.Module):
    """New state = trunk(cat(x, previous state or zeros)); the output is the new state."""

    def __init__(self, channels: int, num_block: int) -> None:
        super().__init__()
        self.forward_trunk = _ConvResTrunk(2 * channels, channels, num_block)

    def forward(self, x: Tensor, state: Tensor | None) -> Tensor:
        if state is None:
            state = torch.zeros_like(x)
        return self.forward_trunk(torch.cat([x, state], 1))


class _LayerNorm2d(nn.Module):
    """Layer norm over the channels of a :math:`(B, C, H, W)` map (biased variance, eps inside the root)."""

    def __init__(self, channels: int, eps: float = 1e-6) -> None:
        super().__init__()
        self.weight = nn.Parameter(torch.ones(channels))
        self.bias = nn.Parameter(torch.zeros(channels))
        self.eps = eps

    def forward(self, x: Tensor) -> Tensor:
        mu = x.mean(1, keepdim=True)
        var = (x - mu).pow(2).mean(1, keepdim=True)
        y = (x - mu) / (var + self.eps).sqrt()
        return self.weight.view(1, -1, 1, 1) * y + self.bias.view(1, -1, 1, 1)


def _squeeze_excite(channels: int) -> nn.Sequential:
    return nn.Sequential(nn.AdaptiveAvgPool2d(1), nn.Conv2d(channels, channels // 2, 1), nn.ReLU(),
                         nn.Conv2d(channels // 2, channels, 1), nn.Sigmoid())


class _AttentionFusion(nn.Module):
    """Event-guided adaptive channel attention fusing event and image features (c -> c_out channels)."""

    def __init__(self, c: int, c_out: int) -> None:
        super().__init__()
        self.beta = nn.Parameter(torch.zeros(1, c, 1, 1))
        self.gamma = nn.Parameter(torch.zeros(1, c_out, 1, 1))
        self.conv1 = nn.Conv2d(c, c, 1)
        self.conv2 = nn.Conv2d(c, c, 3, 1, 1, groups=c)
        self.conv1_e = nn.Conv2d(c, c, 1)
        self.conv2_e = nn.Conv2d(c, c, 3, 1, 1, groups=c)
        self.conv3 = nn.Conv2d(2 * c, c, 1)
        self.se_1 = _squeeze_excite(c)
        self.se_2 = _squeeze_excite(c)  # in the official state_dict, never used
        self.conv4 = nn.Conv2d(c, 2 * c, 1)
        self.conv5 = nn.Conv2d(2 * c, c_out, 1)
        self.conv_y_side = nn.Conv2d(c, c_out, 1)
        self.norm1 = _LayerNorm2d(c)
        self.norm1_e = _LayerNorm2d(c)
        self.norm2 = _LayerNorm2d(c)

    def forward(self, event_feat: Tensor, image_feat: Tensor) -> Tensor:
        img = F.gelu(self.conv2(self.conv1(self.norm1(image_feat))))
        ev = F.gelu(self.conv2_e(self.conv1_e(self.norm1_e(event_feat))))
        img = img * self.se_1(ev)
        ev = ev * self.se_1(ev)
        y = event_feat + image_feat + self.conv3(torch.cat((img, ev), 1)) * self.beta
        ffn = self.conv5(F.gelu(self.conv4(self.norm2(y))))
        return self.conv_y_side(y) + ffn * self.gamma


class _EventEncoder(nn.Module):
    """One scale of an event encoder: fuse image features, recurrent cell, (fuse directions), downsample."""

    def __init__(self, cin: int, cout: int, num_block: int, attention: bool, two_directions: bool) -> None:
        super().__init__()
        self.conv = _ConvAct(cin, cout, 3, 1, 0.2)  # unused at the attention scale (as officially)
        if attention:
            self.atten_fuse = _AttentionFusion(cin, cout)
        self.attention = attention
        self.recurrent_block = _RecurrentCell(cout, num_block)
        if two_directions:
            self.fuse_two_dir = _ConvAct(2 * cout, cout, 1, 0, 0.2)
        self.down = nn.Conv2d(cout, cout, 4, 2, 1, bias=False)

    def forward(self, x: Tensor, image: Tensor | None, state: Tensor | None,
                other_direction: Tensor | None = None, downsample: bool = True) -> tuple[Tensor | None, Tensor]:
        if image is not None and self.attention:
            x = self.atten_fuse(x, image)
        else:
            if image is not None:
                x = x + image
            x = F.leaky_relu(self.conv(x), 0.2)  # ConvLayer's LeakyReLU(0.2), then the layer's own again
        state = self.recurrent_block(x, state)
        x = state
        if other_direction is not None:
            x = self.fuse_two_dir(torch.cat((x, other_direction), 1))
        return (self.down(x) if downsample else None), state


class _ImageEncoder(nn.Module):
    """``lrelu(conv_2(lrelu(conv_1(x)))) + identity(x)``, then a stride-2 4x4 conv."""

    def __init__(self, cin: int, cout: int) -> None:
        super().__init__()
        self.identity = nn.Conv2d(cin, cout, 1)
        self.conv_1 = nn.Conv2d(cin, cout, 3, 1, 1)
        self.conv_2 = nn.Conv2d(cout, cout, 3, 1, 1)
        self.down = nn.Conv2d(cout, cout, 4, 2, 1, bias=False)

    def forward(self, x: Tensor) -> Tensor:
        out = F.leaky_relu(self.conv_2(F.leaky_relu(self.conv_1(x), 0.2)), 0.2)
        return self.down(out + self.identity(x))


class _ResBlock(nn.Module):
    """``relu(conv2(relu(conv1(x))) + x)``."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(channels, channels, 3, 1, 1)
        self.conv2 = nn.Conv2d(channels, channels, 3, 1, 1)

    def forward(self, x: Tensor) -> Tensor:
        return F.relu(self.conv2(F.relu(self.conv1(x))) + x)


class _Decoder(nn.Module):
    """2x transposed conv, then a recurrent cell on ``cat(upsampled, previous state or zeros)``."""

    def __init__(self, cin: int, cout: int) -> None:
        super().__init__()
        self.transposed_conv2d = nn.ConvTranspose2d(cin, cout, 2, stride=2)
        self.forward_trunk = _ConvResTrunk(2 * cout, cout, 1)

    def forward(self, x: Tensor, state: Tensor | None) -> Tensor:
        up = self.transposed_conv2d(x)
        if state is None:
            state = torch.zeros_like(up)
        return self.forward_trunk(torch.cat([up, state], 1))


class REFIDNet(nn.Module):
    """The REFID network (official ``FinalBidirectionAttenfusion``), state_dict compatible with it.

    An image encoder reads the blurry frame(s) and their in-exposure voxel bins once; a bidirectional
    recurrent event encoder runs over the ``T`` event bin pairs (backward, then forward), fused with the
    image features by channel attention at the second scale and by addition at the others; a recurrent
    decoder outputs one frame per bin pair.

    Args:
        img_chn: channels of ``x``: 26 for blurry frame interpolation with m = 11 (``2m + 4``), 13 for
            single-frame deblurring (``m + 2``), 6 for sharp frame interpolation.
        ev_chn: channels of each event step (2: a pair of voxel bins).
        out_chn: output channels.
        num_encoders: scales; ``H`` and ``W`` must be multiples of ``2**num_encoders``.
        base_num_channels: channels at full resolution.
        num_block: residual blocks in each recurrent cell.
        num_residual_blocks: residual blocks in the bottleneck.

    Returns (forward):
        :math:`(B, T, 3, H, W)`, raw (not clamped, no activation), one frame per event step.

    Example:
        >>> net = REFIDNet()
        >>> sum(p.numel() for p in net.parameters())
        15928355
        >>> net(torch.rand(1, 26, 8, 8), torch.randn(1, 3, 2, 8, 8)).shape
        torch.Size([1, 3, 3, 8, 8])
    """

    def __init__(self, img_chn: int = 26, ev_chn: int = 2, out_chn: int = 3, num_encoders: int = 3,
                 base_num_channels: int = 32, num_block: int = 1, num_residual_blocks: int = 2) -> None:
        super().__init__()
        for name, v in (("img_chn", img_chn), ("ev_chn", ev_chn), ("out_chn", out_chn),
                        ("num_encoders", num_encoders), ("base_num_channels", base_num_channels),
                        ("num_block", num_block)):
            if v < 1:
                raise ValueError(f"{name} must be >= 1, got {v}")
        self.img_chn, self.ev_chn, self.out_chn = img_chn, ev_chn, out_chn
        self.num_encoders = num_encoders
        c = base_num_channels
        sizes = [(c * 2 ** i, c * 2 ** (i + 1)) for i in range(num_encoders)]
        self.head = _ConvAct(ev_chn, c, 5, 2, 0.2)
        self.encoders_backward = nn.ModuleList(
            [_EventEncoder(cin, cout, num_block, i == 1, False) for i, (cin, cout) in enumerate(sizes)])
        self.encoders_forward = nn.ModuleList(
            [_EventEncoder(cin, cout, num_block, i == 1, True) for i, (cin, cout) in enumerate(sizes)])
        self.head_img = _ConvAct(img_chn, c, 5, 2, 0.2)
        self.img_encoders = nn.ModuleList([_ImageEncoder(cin, cout) for cin, cout in sizes])
        top = c * 2 ** num_encoders
        self.resblocks = nn.ModuleList([_ResBlock(top) for _ in range(num_residual_blocks)])
        self.decoders = nn.ModuleList([_Decoder(cout, cout // 2) for _, cout in reversed(sizes)])
        self.pred = _ConvAct(c, out_chn, 3, 1, None)

    def extra_repr(self) -> str:
        return f"img_chn={self.img_chn}, ev_chn={self.ev_chn}, out_chn={self.out_chn}"

    def forward(self, x: Tensor, event: Tensor) -> Tensor:
        """Restore ``T`` frames.

        Args:
            x: image input :math:`(B, C_{img}, H, W)`, or :math:`(B, N, C, H, W)` flattened to ``N*C``.
            event: event steps :math:`(B, T, C_{ev}, H, W)`.

        Returns:
            :math:`(B, T, C_{out}, H, W)`.
        """
        if not isinstance(x, Tensor) or x.dim() not in (4, 5):
            raise ValueError(f"x must be a (B, C, H, W) or (B, N, C, H, W) tensor, got "
                             f"{tuple(x.shape) if isinstance(x, Tensor) else type(x).__name__}")
        if x.dim() == 5:
            x = x.flatten(1, 2)
        if not isinstance(event, Tensor) or event.dim() != 5:
            raise ValueError(f"event must be a (B, T, {self.ev_chn}, H, W) tensor, got "
                             f"{tuple(event.shape) if isinstance(event, Tensor) else type(event).__name__}")
        b, t, ce, h, w = event.shape
        if ce != self.ev_chn or x.shape[1] != self.img_chn:
            raise ValueError(f"expected x with {self.img_chn} channels and event with {self.ev_chn}, got x "
                             f"{tuple(x.shape)} and event {tuple(event.shape)}")
        if x.shape[0] != b or tuple(x.shape[-2:]) != (h, w):
            raise ValueError(f"x {tuple(x.shape)} and event {tuple(event.shape)} disagree on B, H or W")
        k = 2 ** self.num_encoders
        if h % k or w % k:
            raise ValueError(f"H and W must be multiples of {k} for REFID, got (H, W)=({h}, {w})")
        if t < 1:
            raise ValueError("event must have at least one step (T >= 1)")

        head = self.head_img(x)
        x_blocks = []
        feat = head
        for encoder in self.img_encoders:
            feat = encoder(feat)
            x_blocks.append(feat)
        e = self.head(event.flatten(0, 1)).unflatten(0, (b, t))

        # backward pass over T-1 .. 0. Only its final states are used: the official loop stores the same
        # list object for every frame, so every forward frame gets the states computed at frame 0.
        back: list[Tensor | None] = [None] * self.num_encoders
        last = self.num_encoders - 1
        for frame in range(t - 1, -1, -1):
            cur: Tensor | None = e[:, frame]
            for i, encoder in enumerate(self.encoders_backward):
                cur, back[i] = encoder(cur, None if i == 0 else x_blocks[i - 1], back[i], downsample=i < last)

        fwd: list[Tensor | None] = [None] * self.num_encoders
        dec: list[Tensor | None] = [None] * len(self.decoders)
        outputs = []
        for frame in range(t):
            cur = e[:, frame]
            skips = []
            for i, encoder in enumerate(self.encoders_forward):
                cur, fwd[i] = encoder(cur, None if i == 0 else x_blocks[i - 1], fwd[i], back[i])
                skips.append(cur)
            for i, block in enumerate(self.resblocks):
                cur = block(cur + x_blocks[-1] if i == 0 else cur)
            for i, decoder in enumerate(self.decoders):
                cur = dec[i] = decoder(cur + skips[self.num_encoders - 1 - i], dec[i])
            outputs.append(self.pred(cur + head))
        return torch.stack(outputs, 1)


# --------------------------------------------------------------------------------------------------
# event representation and input layout
# --------------------------------------------------------------------------------------------------
def refid_voxel_grid(events: Events, t_start: Tensor | float, t_end: Tensor | float, num_bins: int,
                     normalize: str = "events") -> Tensor:
    """REFID's voxel grid: events split bilinearly in time between neighbouring bins (E2VID style).

    The events with ``t_start <= t < t_end`` of each sample are mapped to ``[0, num_bins - 1]``; an
    event at position ``u`` puts ``p (1 - frac(u))`` in bin ``floor(u)`` and ``p frac(u)`` in the next one
    (dropped past the last bin). Values are the signed sums, not normalised (as the network was trained:
    the official normalisation is a no-op).

    Args:
        events: the events (polarity ±1).
        t_start: window start :math:`(B,)` or a scalar, µs.
        t_end: window end :math:`(B,)` or a scalar, µs.
        num_bins: number of bins.
        normalize: ``"events"`` (official): the first and last event of the window are mapped to 0 and
            ``num_bins - 1`` (all events to bin 0 when they share one timestamp), so the bins follow the
            events: shifting every event by the same latency changes nothing but which events are in the
            window. ``"window"``: ``t_start`` and ``t_end`` are mapped to 0 and ``num_bins - 1`` (a fixed
            time axis: a latency moves events between bins).

    Returns:
        :math:`(B, num\\_bins, H, W)` float32.

    Example:
        >>> ev = Events(torch.tensor([0, 1]), torch.tensor([0, 0]), torch.tensor([0.0, 37.5]),
        ...             torch.tensor([1, -1]), sensor_size=(1, 2))
        >>> refid_voxel_grid(ev, 0.0, 100.0, 5, normalize="window")[0, :, 0].tolist()
        [[1.0, 0.0], [0.0, -0.5], [0.0, -0.5], [0.0, 0.0], [0.0, 0.0]]
    """
    if not isinstance(events, Events):
        raise ValueError(f"events must be evlatcorr.Events, got {type(events).__name__}")
    check_int(num_bins, "num_bins")
    if normalize not in _NORMALIZE:
        raise ValueError(f"normalize must be one of {_NORMALIZE}, got {normalize!r}")
    bsz = events.batch_size
    height, width = events.sensor_size
    device = events.device
    start = torch.as_tensor(t_start, dtype=torch.float64, device=device)
    end = torch.as_tensor(t_end, dtype=torch.float64, device=device)
    ev = events.window(start, end)  # validates the shapes and end >= start
    start, end = start.expand(bsz), end.expand(bsz)
    grid = torch.zeros(bsz * num_bins * height * width, dtype=torch.float64, device=device)
    if len(ev):
        b = ev.batch
        if normalize == "events":
            lo = torch.full((bsz,), math.inf, dtype=torch.float64, device=device).scatter_reduce(
                0, b, ev.t, "amin")
            hi = torch.full((bsz,), -math.inf, dtype=torch.float64, device=device).scatter_reduce(
                0, b, ev.t, "amax")
        else:
            lo, hi = start, end
        span = hi - lo
        span = torch.where(span == 0, torch.ones_like(span), span)
        u = (num_bins - 1) * (ev.t - lo[b]) / span[b]
        left = torch.floor(u)
        frac = u - left
        pol = ev.p.to(torch.float64)
        index = ((b * num_bins + left.long()) * height + ev.y) * width + ev.x
        keep = left < num_bins
        grid.index_add_(0, index[keep], (pol * (1.0 - frac))[keep])
        keep = left + 1 < num_bins
        grid.index_add_(0, index[keep] + height * width, (pol * frac)[keep])
    return grid.view(bsz, num_bins, height, width).to(torch.float32)


def _check_layout(m: int, n: int, mode: str, frame_offset: float) -> None:
    if mode not in _MODES:
        raise ValueError(f"mode must be one of {_MODES}, got {mode!r}")
    check_int(m, "m (sharp frames per blurry frame)", minimum=2)
    check_int(n, "n (sharp frames between two blurry frames)", minimum=0)
    if not 0.0 <= float(frame_offset) <= 1.0:
        raise ValueError(f"frame_offset must be in [0, 1] (sharp-frame intervals), got {frame_offset}")


def _span(frames: EventFrames, mode: str) -> tuple[Tensor, Tensor]:
    if not isinstance(frames, EventFrames):
        raise ValueError(f"REFID takes an EventFrames batch, got {type(frames).__name__}")
    if mode == "deblur":
        return frames.exposure_start, frames.exposure_end
    if frames.blurry_next is None or frames.exposure_end_next is None:
        raise ValueError("REFID interpolation needs frames.blurry_next with exposure_start_next and "
                         "exposure_end_next (the right blurry frame); use mode='deblur' for single frames")
    if bool((frames.exposure_start_next < frames.exposure_end).any()):
        raise ValueError("REFID interpolation needs the next exposure to start after the first one ends")
    return frames.exposure_start, frames.exposure_end_next


def refid_window(frames: EventFrames, m: int = 11, n: int = 1, mode: str = "interpolation",
                 frame_offset: float = 0.5) -> tuple[Tensor, Tensor, Tensor]:
    """The voxel window and sharp-frame spacing of REFID's data layout (see the module docstring).

    Args:
        frames: the batch (``blurry_next`` and its exposure are needed for interpolation).
        m: sharp frames per blurry frame.
        n: sharp frames between the two blurry frames (interpolation).
        mode: ``"interpolation"`` or ``"deblur"``.
        frame_offset: position of the first sharp frame after the exposure start, in sharp-frame
            intervals: 0.5 when the exposure is the integration interval, 0 when ``exposure_start`` and
            ``exposure_end`` are the first and last sharp-frame times (HighREV reader).

    Returns:
        ``(start, end, delta)``, each :math:`(B,)` float64 µs: the window holds ``2m + n + 1``
        (interpolation) or ``m + 1`` (deblurring) sharp-frame intervals of ``delta``.

    Example:
        >>> from evlatcorr import Events
        >>> ev = Events(torch.zeros(1), torch.zeros(1), torch.tensor([5.0]), torch.ones(1), sensor_size=(8, 8))
        >>> fr = EventFrames(torch.rand(1, 3, 8, 8), ev, torch.tensor([0.0]), torch.tensor([110.0]))
        >>> [v.item() for v in refid_window(fr, mode="deblur")]
        [-5.0, 115.0, 10.0]
    """
    _check_layout(m, n, mode, frame_offset)
    s, e = _span(frames, mode)
    frames_inside = (2 * m + n) if mode == "interpolation" else m  # sharp frames from s to e
    delta = (e - s) / (frames_inside - 1 + 2 * float(frame_offset))
    margin = (1.0 - float(frame_offset)) * delta
    return s - margin, e + margin, delta


def refid_output_times(frames: EventFrames, m: int = 11, n: int = 1, mode: str = "interpolation",
                       frame_offset: float = 0.5) -> Tensor:
    """Times of REFID's output frames :math:`(B, T)` in µs (float64): ``T = 2m + n`` or ``m``.

    Output ``k`` is the sharp frame ``exposure_start + (k + frame_offset) delta`` (see :func:`refid_window`).

    Example:
        >>> from evlatcorr import Events
        >>> ev = Events(torch.zeros(1), torch.zeros(1), torch.tensor([5.0]), torch.ones(1), sensor_size=(8, 8))
        >>> fr = EventFrames(torch.rand(1, 3, 8, 8), ev, torch.tensor([0.0]), torch.tensor([110.0]))
        >>> refid_output_times(fr, mode="deblur")[0, [0, 5, 10]].tolist()
        [5.0, 55.0, 105.0]
    """
    _, _, delta = refid_window(frames, m, n, mode, frame_offset)
    t = (2 * m + n) if mode == "interpolation" else m
    k = torch.arange(t, dtype=torch.float64, device=delta.device)
    return frames.exposure_start[:, None] + (k[None, :] + float(frame_offset)) * delta[:, None]


def refid_inputs(frames: EventFrames, m: int = 11, n: int = 1, mode: str = "interpolation",
                 frame_offset: float = 0.5, normalize: str = "events") -> tuple[Tensor, Tensor]:
    """Build REFID's network inputs from a batch, in the official layout.

    Events are ``frames.corrected`` when a corrector filled it, else ``frames.events``. Grey frames are
    repeated to RGB.

    Args:
        frames: the batch; interpolation uses ``blurry`` and ``blurry_next``.
        m: sharp frames per blurry frame; by default 4 for ``None`` / ``"default"`` (the shipped 4+1 weights),
            read from the weights' input channels for a file (11 for the released weights), 11 for ``"deblur"``.
        n: sharp frames between the blurry frames (1 or 3 for the released weights).
        mode: ``"interpolation"`` (two blurry frames) or ``"deblur"`` (one).
        frame_offset: see :func:`refid_window`.
        normalize: timestamp mapping of :func:`refid_voxel_grid` (``"events"`` is the official one).

    Returns:
        ``(x, event)``: interpolation: ``x`` :math:`(B, 2m+4, H, W)` = cat(left RGB, voxel[1:m], right RGB,
        voxel[m+n+2:]) and ``event`` :math:`(B, 2m+n, 2, H, W)` (bin pairs of a ``2m+n+1`` bin grid);
        deblurring: ``x`` :math:`(B, m+2, H, W)` = cat(RGB, voxel[1:-1]) and ``event`` :math:`(B, m, 2, H, W)`.

    Example:
        >>> ev = Events(torch.tensor([1, 2]), torch.tensor([3, 4]), torch.tensor([10.0, 150.0]),
        ...             torch.tensor([1, 0]), sensor_size=(8, 8))
        >>> fr = EventFrames(torch.rand(1, 3, 8, 8), ev, torch.tensor([0.0]), torch.tensor([110.0]),
        ...                  blurry_next=torch.rand(1, 3, 8, 8), exposure_start_next=torch.tensor([120.0]),
        ...                  exposure_end_next=torch.tensor([230.0]))
        >>> [tuple(v.shape) for v in refid_inputs(fr)]
        [(1, 26, 8, 8), (1, 23, 2, 8, 8)]
    """
    start, end, _ = refid_window(frames, m, n, mode, frame_offset)
    events = NetworkAdapter.input_events(frames)
    num_bins = (2 * m + n + 1) if mode == "interpolation" else (m + 1)
    voxel = refid_voxel_grid(events, start, end, num_bins, normalize).to(frames.device)
    event = torch.stack((voxel[:, :-1], voxel[:, 1:]), 2)
    left = rgb(frames.blurry).to(voxel.dtype)
    if mode == "deblur":
        x = torch.cat((left, voxel[:, 1:-1]), 1)
    else:
        assert frames.blurry_next is not None  # checked by refid_window
        right = rgb(frames.blurry_next).to(voxel.dtype)
        x = torch.cat((left, voxel[:, 1:m], right, voxel[:, m + n + 2:]), 1)
    return x, event


def nearest_frames(output: Tensor, output_times: Tensor, target_times: Tensor) -> Tensor:
    """The output frame nearest each target time.

    Args:
        output: :math:`(B, T, C, H, W)`.
        output_times: :math:`(B, T)` µs.
        target_times: :math:`(B, T')` µs.

    Returns:
        :math:`(B, T', C, H, W)`.

    Example:
        >>> out = torch.arange(3.0).view(1, 3, 1, 1, 1)
        >>> nearest_frames(out, torch.tensor([[0.0, 10.0, 20.0]]), torch.tensor([[12.0, 1.0]])).flatten().tolist()
        [1.0, 0.0]
    """
    if output.dim() != 5 or output_times.shape != output.shape[:2]:
        raise ValueError(f"output (B, T, C, H, W) and output_times (B, T) must agree, got {tuple(output.shape)} "
                         f"and {tuple(output_times.shape)}")
    if target_times.dim() != 2 or target_times.shape[0] != output.shape[0]:
        raise ValueError(f"target_times must be (B, T') with B={output.shape[0]}, got {tuple(target_times.shape)}")
    dist = (output_times[:, None, :].to(torch.float64) - target_times[:, :, None].to(torch.float64)).abs()
    index = dist.argmin(-1).to(output.device)  # (B, T')
    return torch.gather(output, 1, index[:, :, None, None, None].expand(-1, -1, *output.shape[2:]))


# --------------------------------------------------------------------------------------------------
# adapter
# --------------------------------------------------------------------------------------------------
SHIPPED_M = 4  # sharp frames per blurry frame of the shipped interpolation weights (checkpoints/refid-4-1)
OFFICIAL_M = 11  # of the released REFID weights (REFID-*-11-1.pth, REFID-*-11-3.pth)


def _default_m(checkpoint: str | Path | None, mode: str) -> int:
    """``m`` when the caller gives none: the shipped layout for ``None`` / ``"default"``; for a file, read
    from its first image convolution (``2m + 4`` input channels), else the released weights' 11."""
    if mode != "interpolation":
        return OFFICIAL_M  # a deblur network's channels (m + 2) cannot tell its m from an interpolation one's
    if checkpoint is None or str(checkpoint) == "default":
        return SHIPPED_M
    from evlatcorr.adapters.checkpoint import load_state_dict_file

    path = Path(checkpoint).expanduser()
    if not (path.is_file() or path.name.endswith(".safetensors")):
        return OFFICIAL_M  # resolve_checkpoint raises the missing-file error
    state = load_state_dict_file(path)
    weight = next((v for k, v in state.items() if k.endswith("head_img.conv2d.weight") and v.dim() == 4), None)
    if weight is None or weight.shape[1] < 8 or weight.shape[1] % 2:
        return OFFICIAL_M  # not REFID weights: load_weights names the mismatch
    return (int(weight.shape[1]) - 4) // 2


class REFIDAdapter(NetworkAdapter):
    """REFID on an :class:`~evlatcorr.frames.EventFrames` batch.

    Reads ``frames.corrected`` when a corrector filled it, else ``frames.events``, so
    ``nn.Sequential(EventLatencyCorrector(), REFIDAdapter(checkpoint=...))`` restores with corrected events.

    Args:
        checkpoint: ``None`` (random weights), a path (official BasicSR ``.pth``, Lightning ``.ckpt``,
            state_dict, our ``.safetensors``) or ``"default"`` (shipped weights: ``checkpoints/refid-4-1``;
            ``refid`` for 11+1, ``refid-<m>-<n>`` for other interpolation settings, ``refid-deblur`` for
            deblurring, where present).
        mode: ``"interpolation"`` (``2m+n`` frames from ``blurry`` and ``blurry_next``; the released 11+1 and
            11+3 weights) or ``"deblur"`` (``m`` frames across one exposure; needs weights trained for it).
        m: sharp frames per blurry frame; by default 4 for ``None`` / ``"default"`` (the shipped 4+1 weights),
            read from the weights' input channels for a file (11 for the released weights), 11 for ``"deblur"``.
        n: sharp frames between two blurry frames: 1 (REFID-*-11-1.pth) or 3 (REFID-*-11-3.pth). The network's
            shape does not depend on ``n``: pass the one the weights were trained with (ideally the
            data's gap is about ``n · exposure / m``).
        frame_offset: see :func:`refid_window`.
        normalize: ``"events"`` (official timestamp mapping) or ``"window"``, see :func:`refid_voxel_grid`.
        pad: pad H and W to multiples of 8 (replicated image border, no events) and crop the output
            (default, so any sensor size runs); when False, such sizes raise a ValueError.
        select: ``"all"`` (every output frame) or ``"nearest"`` (the frame nearest each
            ``frames.target_times``).
        clamp: clamp ``output`` to [0, 1] (training leaves it off so every pixel gets a gradient).

    Returns (forward):
        ``frames`` with ``output`` :math:`(B, T, C, H, W)`, clamped to [0, 1] by default (C as ``blurry``: grey input is
        read as RGB and the output's channel mean is returned), and ``meta["output_times"]``
        :math:`(B, T)` µs, the time of each output frame.

    Example:
        >>> adapter = REFIDAdapter()  # random weights in the shipped 4+1 layout; or checkpoint="default"
        >>> adapter.net.img_chn, adapter.extra_repr()
        (12, 'mode=interpolation, m=4, n=1, frame_offset=0.5, normalize=events, pad=True, select=all')
        >>> REFIDAdapter(m=11).net.img_chn  # the layout of the released REFID-GoPro-11-1.pth
        26
    """

    model_name = "REFID"
    short_repr = False  # REFIDAdapter has always printed its whole network

    def __init__(self, checkpoint: str | None = None, mode: str = "interpolation", m: int | None = None, n: int = 1,
                 frame_offset: float = 0.5, normalize: str = "events", pad: bool = True,
                 select: str = "all", clamp: bool = True) -> None:
        super().__init__()
        if m is None:
            m = _default_m(checkpoint, mode)
        _check_layout(m, n, mode, frame_offset)
        if normalize not in _NORMALIZE:
            raise ValueError(f"normalize must be one of {_NORMALIZE}, got {normalize!r}")
        if select not in ("all", "nearest"):
            raise ValueError(f"select must be 'all' or 'nearest', got {select!r}")
        self.mode, self.m, self.n, self.frame_offset = mode, m, n, float(frame_offset)
        self.normalize, self.pad, self.select, self.clamp = normalize, bool(pad), select, bool(clamp)
        self.net = REFIDNet(img_chn=(2 * m + 4) if mode == "interpolation" else (m + 2))
        if mode == "deblur":
            name = "refid-deblur"
        else:
            name = "refid" if (m, n) == (11, 1) else f"refid-{m}-{n}"
        self.load_checkpoint(checkpoint, name)
        self.net.eval()

    def extra_repr(self) -> str:
        return (f"mode={self.mode}, m={self.m}, n={self.n}, frame_offset={self.frame_offset}, "
                f"normalize={self.normalize}, pad={self.pad}, select={self.select}")

    def forward(self, frames: EventFrames) -> EventFrames:
        self.check_frames(frames, image=False)
        padding = self.padding(*frames.sensor_size, 2 ** self.net.num_encoders)
        if self.select == "nearest" and frames.target_times is None:
            raise ValueError("select='nearest' needs frames.target_times (B, T) in us")
        x, event = refid_inputs(frames, self.m, self.n, self.mode, self.frame_offset, self.normalize)
        times = refid_output_times(frames, self.m, self.n, self.mode, self.frame_offset)
        param = next(self.net.parameters())
        x, event = self.pad_inputs(padding, x.to(param), event.to(param))
        out = self.finish(self.net(x, event), frames)
        if self.select == "nearest":
            assert frames.target_times is not None
            out = nearest_frames(out, times, frames.target_times)
            times = nearest_frames(times[:, :, None, None, None], times, frames.target_times).flatten(2)[..., 0]
        return frames.replace(output=out, meta={**frames.meta, "output_times": times})
