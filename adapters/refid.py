"""REFID (Sun et al., CVPR 2023, "Event-Based Frame Interpolation with Ad-hoc Deblurring") as an adapter.

A re-implementation of the official network (``FinalBidirectionAttenfusion`` in AHupuJR/REFID,
``basicsr/models/archs/XXNet_final_attenfusion_arch.py``, commit f94eb19) whose ``state_dict`` has the
official key names and shapes, so the released BasicSR ``.pth`` weights load with ``strict=True`` and give
the official outputs number for number (see ``tests/test_adapters_refid.py``; the network is
:mod:`evlatcorr.adapters.refid_net`), plus the official event representation and input layout.

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
from torch import Tensor

from evlatcorr.adapters.base import NetworkAdapter, rgb
from evlatcorr.adapters.refid_net import REFIDNet
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

    @torch.compiler.disable  # events of data-dependent sizes: torch.compile compiles the network, not this
    def representation(self, frames: EventFrames) -> tuple[Tensor, Tensor]:
        """The network's inputs: the blurry frames and the events' voxel grids (:func:`refid_inputs`)."""
        return refid_inputs(frames, self.m, self.n, self.mode, self.frame_offset, self.normalize)

    def forward(self, frames: EventFrames) -> EventFrames:
        self.check_frames(frames, image=False)
        padding = self.padding(*frames.sensor_size, 2 ** self.net.num_encoders)
        if self.select == "nearest" and frames.target_times is None:
            raise ValueError("select='nearest' needs frames.target_times (B, T) in us")
        x, event = self.representation(frames)
        times = refid_output_times(frames, self.m, self.n, self.mode, self.frame_offset)
        param = next(self.net.parameters())
        x, event = self.pad_inputs(padding, x.to(param), event.to(param))
        out = self.finish(self.net(x, event), frames)
        if self.select == "nearest":
            assert frames.target_times is not None
            out = nearest_frames(out, times, frames.target_times)
            times = nearest_frames(times[:, :, None, None, None], times, frames.target_times).flatten(2)[..., 0]
        return frames.replace(output=out, meta={**frames.meta, "output_times": times})
