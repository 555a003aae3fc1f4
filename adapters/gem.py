"""GEM (Zhang et al., ICCV 2023, "Generalizing Event-Based Motion Deblurring in Real-World Scenarios").

A re-implementation of GEM's scale-aware network (``San`` in XiangZ-0/GEM, ``codes/model/san.py``, commit
33891b3, ``San(im_in_channel=3, out_channel=3, ev_in_channel=96)``, 2,421,882 parameters) whose
``state_dict`` has the official key names and shapes, so the released Lightning checkpoints load with
``strict=True`` (the ``model.`` prefix is stripped, the ``teacher_model.`` copy ignored), plus the official
event representation (EGER) and an adapter that runs it on an :class:`~evlatcorr.frames.EventFrames` batch.

Network in brief. Two encoders of the same structure, one for the blurry image (at image resolution
``H x W``) and one for the EGER (at event-sensor resolution ``h x w``, which need not be ``H x W``), give
five feature scales each (16, 32, 64, 128, 128 channels, halved by average pooling). At every scale a
multi-scale feature fusion (MSFF) block queries the event features at the image-feature grid with a local
implicit function (LIIF-style: the four nearest event cells, an MLP on ``[event feature, relative
coordinate, relative cell size, image feature]``, area-weighted) and refines the result with a modulated
deformable convolution (DCNv2, run through :func:`torchvision.ops.deform_conv2d`). A U-Net decoder with
bicubic upsampling predicts a per-pixel, per-channel ratio ``E = softplus(decoder) > 0`` and the latent
sharp image is ``L = blurry * E``. ``forward(event, blur)`` returns ``(L, E)`` (``L`` not clamped).

Event representation (:func:`gem_eger`, the official ``codes/data/utils.py`` ``gen_EGER``): the events of
the exposure ``[start, end)`` are counted in 16 equal time bins over the exposure, split into three segments
by the target window ``[target_start, target_end)`` (before / inside / after) and two polarities, giving 96
channels ``bin * 6 + segment * 2 + polarity``. The official test deblurs to a single time ``ts`` (the
target window is ``(ts, ts)``, so the middle segment is empty); with ``predict_ts=0.5`` (its MS-RBD
configuration) ``ts = start + 0.5 (end - start)``, the mid-exposure frame, which is what
:class:`GEMAdapter` does unless ``frames.target_times`` asks for another time.

Spatial scale. The official loaders keep the events at the event sensor's resolution and the image at its
own: ``scale_factor = H_image / H_events`` is 4 for Ev-REDS and MS-RBD (DAVIS346 events behind a 4x
larger RGB frame) and 1 for HS-ERGB. Our data (DAVIS-style, and HighREV used in the latency-correction
paper) have pixel-aligned events and frames, so the adapter's default is ``scale_factor=1``: the EGER is
built at ``H x W``, which is the official HS-ERGB configuration. ``scale_factor=s > 1`` mimics the 4x
configurations by binning the event coordinates to a ``(H // s, W // s)`` grid (``x // s, y // s``; counts of
the ``s x s`` pixels of a cell are summed, as a low-resolution sensor has no pixels to share them between;
events beyond the grid are dropped like the official region of interest).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn
from torchvision.ops import deform_conv2d

from evlatcorr.adapters.base import NetworkAdapter, rgb
from evlatcorr.checks import check_batch_vector, check_int, check_shape
from evlatcorr.events import Events
from evlatcorr.frames import EventFrames

__all__ = ["SAN", "GEMAdapter", "San", "gem_eger"]

NUM_PARAMETERS = 2_421_882  # official San(3, 3, 96)
SEGMENTS = 3  # before / inside / after the target window
DIVISOR = 16  # four 2x average poolings with skip connections at image resolution
MIN_EVENT_SIZE = 16  # the event encoder pools four times too


# event representation --------------------------------------------------------------------------
def gem_eger(events: Events, exposure_start: Tensor | float, exposure_end: Tensor | float,
             target_start: Tensor | float | None = None, target_end: Tensor | float | None = None,
             num_bins: int = 16, scale_factor: int = 1) -> Tensor:
    """GEM's exposure-guided event representation (EGER) of the events in each exposure.

    For sample ``b``, the events with ``exposure_start[b] <= t < exposure_end[b]`` are counted (not
    normalised) in the cell ``(y // scale_factor, x // scale_factor)`` of channel
    ``bin * 6 + segment * 2 + polarity`` where

    * ``bin = floor((t - start) / interval)``, ``interval = (end - start) / num_bins``; an index equal to
      ``num_bins`` (rounding at the very end of the exposure) goes to the last bin;
    * ``segment`` is 0 for ``t < target_start``, 1 for ``target_start <= t < target_end``, 2 otherwise;
    * ``polarity`` is 0 for negative and 1 for positive events.

    Deblurring to one time ``ts`` uses ``target_start = target_end = ts`` (segment 1 is then empty), as the
    official test does. The official loader truncates ``start`` to whole microseconds when computing the
    bin (``t -= int(exp_start)``); its timestamps are integers, where this makes no difference, so
    ``start`` is used as is here.

    Args:
        events: events with ``sensor_size`` :math:`(H, W)` and ``batch_size`` B.
        exposure_start: exposure start of each sample :math:`(B,)` in µs (or a scalar).
        exposure_end: exposure end of each sample :math:`(B,)` in µs (or a scalar).
        target_start: start of the target window :math:`(B,)` in µs; ``None``: mid-exposure,
            ``start + 0.5 (end - start)``.
        target_end: end of the target window :math:`(B,)` in µs, ``>= target_start``; ``None``: equal to
            ``target_start``.
        num_bins: time bins over the exposure (16 for the released models, giving 96 channels).
        scale_factor: image-to-event resolution ratio ``s``: the map is :math:`(H // s, W // s)` and events
            whose cell falls outside it are dropped. 1 for pixel-aligned events (our data, HS-ERGB); the
            released Ev-REDS / MS-RBD models saw events at 1/4 of the image resolution.

    Returns:
        EGER :math:`(B, 6 \\cdot num\\_bins, H // s, W // s)` float32 on the events' device.

    Example:
        >>> ev = Events(torch.tensor([1, 0]), torch.tensor([0, 0]), torch.tensor([10.0, 70.0]),
        ...             torch.tensor([1, -1]), sensor_size=(1, 2))
        >>> eger = gem_eger(ev, 0.0, 160.0)  # 16 bins of 10 us, target at mid-exposure (80 us)
        >>> eger.shape, eger[0, 1 * 6 + 0 * 2 + 1, 0, 1].item(), eger[0, 7 * 6 + 0 * 2 + 0, 0, 0].item()
        (torch.Size([1, 96, 1, 2]), 1.0, 1.0)
    """
    if not isinstance(events, Events):
        raise ValueError(f"events must be evlatcorr.Events, got {type(events).__name__}")
    check_int(num_bins, "num_bins")
    check_int(scale_factor, "scale_factor")
    batch_size = events.batch_size
    height, width = events.sensor_size
    h, w = height // scale_factor, width // scale_factor
    if h < 1 or w < 1:
        raise ValueError(f"scale_factor={scale_factor} is larger than the sensor (H, W)={events.sensor_size}")
    device = events.device
    start = check_batch_vector(exposure_start, batch_size, "exposure_start").to(device, torch.float64)
    end = check_batch_vector(exposure_end, batch_size, "exposure_end").to(device, torch.float64)
    if bool((end <= start).any()):
        raise ValueError("exposure_end must be after exposure_start for every sample")
    if target_start is None:
        if target_end is not None:
            raise ValueError("target_end needs target_start")
        t_lo = start + 0.5 * (end - start)  # the official predict_ts=0.5 formula
        t_hi = t_lo
    else:
        t_lo = check_batch_vector(target_start, batch_size, "target_start").to(device, torch.float64)
        t_hi = t_lo if target_end is None else check_batch_vector(target_end, batch_size, "target_end").to(
            device, torch.float64)
    if bool((t_hi < t_lo).any()):
        raise ValueError("target_end must not be before target_start")
    channels = SEGMENTS * 2 * num_bins
    out = torch.zeros(batch_size * channels * h * w, dtype=torch.float32, device=device)
    ev = events.window(start, end)
    if len(ev):
        cx, cy = ev.x // scale_factor, ev.y // scale_factor
        inside = (cx < w) & (cy < h)
        b, t = ev.batch[inside], ev.t[inside]
        cx, cy, p = cx[inside], cy[inside], ev.p[inside]
        interval = (end - start) / num_bins
        index = torch.floor((t - start[b]) / interval[b]).long().clamp_(0, num_bins - 1)
        segment = (t >= t_lo[b]).long() + (t >= t_hi[b]).long()
        channel = index * (SEGMENTS * 2) + segment * 2 + (p > 0).long()
        flat = ((b * channels + channel) * h + cy) * w + cx
        out.index_add_(0, flat, torch.ones_like(flat, dtype=torch.float32))
    return out.view(batch_size, channels, h, w)


# network ----------------------------------------------------------------------------------------
def _kaiming_init(module: nn.Module) -> None:
    """The official ``init_weights(net, 'kaiming')``: normal fan-in weights, zero biases (conv / linear)."""
    for m in module.modules():
        if isinstance(m, (nn.Conv2d, nn.Linear)):
            nn.init.kaiming_normal_(m.weight, a=0, mode="fan_in")
            if m.bias is not None:
                nn.init.zeros_(m.bias)


class _Down(nn.Module):
    """2x average pooling, then two ReLU convolutions."""

    def __init__(self, in_ch: int, out_ch: int, kernel: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(in_ch, out_ch, kernel, padding=kernel // 2)
        self.conv2 = nn.Conv2d(out_ch, out_ch, kernel, padding=kernel // 2)

    def forward(self, x: Tensor) -> Tensor:
        x = F.avg_pool2d(x, 2)
        return F.relu(self.conv2(F.relu(self.conv1(x))))


class _Up(nn.Module):
    """2x bicubic upsampling, a ReLU convolution, the skip added, another ReLU convolution."""

    def __init__(self, in_ch: int, out_ch: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(in_ch, out_ch, 3, padding=1)
        self.conv2 = nn.Conv2d(out_ch, out_ch, 3, padding=1)

    def forward(self, x: Tensor, skip: Tensor) -> Tensor:
        x = F.interpolate(x, scale_factor=2, mode="bicubic", align_corners=False)
        x = F.relu(self.conv1(x))
        return F.relu(self.conv2(x + skip))


class _Encoder(nn.Module):
    """Five feature scales: 16 channels at full resolution, then 32, 64, 128, 128 at 1/2 .. 1/16."""

    def __init__(self, in_ch: int) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(in_ch, 16, 7, padding=3)
        self.conv2 = nn.Conv2d(16, 16, 7, padding=3)
        self.down1 = _Down(16, 32, 5)
        self.down2 = _Down(32, 64, 3)
        self.down3 = _Down(64, 128, 3)
        self.down4 = _Down(128, 128, 3)

    def forward(self, x: Tensor) -> list[Tensor]:
        feats = [F.relu(self.conv2(F.relu(self.conv1(x))))]
        for down in (self.down1, self.down2, self.down3, self.down4):
            feats.append(down(feats[-1]))
        return feats


class _Decoder(nn.Module):
    def __init__(self, out_ch: int) -> None:
        super().__init__()
        self.up1 = _Up(128, 128)
        self.up2 = _Up(128, 64)
        self.up3 = _Up(64, 32)
        self.up4 = _Up(32, 16)
        self.conv = nn.Conv2d(16, out_ch, 3, padding=1)

    def forward(self, feats: list[Tensor]) -> Tensor:
        x = feats[4]
        for up, skip in zip((self.up1, self.up2, self.up3, self.up4), reversed(feats[:4])):
            x = up(x, skip)
        return self.conv(x)


class _PointMLP(nn.Module):
    """Linear-ReLU stack applied to the last dimension (``layers.0, 2, 4, 6`` are the linear layers)."""

    def __init__(self, in_dim: int, out_dim: int, hidden: list[int]) -> None:
        super().__init__()
        mods: list[nn.Module] = []
        for width in hidden:
            mods += [nn.Linear(in_dim, width), nn.ReLU()]
            in_dim = width
        mods.append(nn.Linear(in_dim, out_dim))
        self.layers = nn.Sequential(*mods)

    def forward(self, x: Tensor) -> Tensor:
        return self.layers(x)


def _cell_centres(size: tuple[int, int], device: torch.device) -> tuple[Tensor, Tensor]:
    """Centres of the cells of a ``size`` grid in [-1, 1] along each axis (float32, as the official code)."""
    out = []
    for n in size:
        r = 1.0 / n
        out.append(-1 + r + (2 * r) * torch.arange(n, device=device).float())
    return out[0], out[1]


class _ImplicitEventQuery(nn.Module):
    """Event features queried at the image-feature grid with a local implicit function.

    Each image-feature pixel ``q`` (centre ``c_q`` in [-1, 1]) looks at four points ``c_q + (±1/h, ±1/w)``
    (``h x w``: event-feature size, plus a 1e-6 nudge), takes the event feature and the image feature
    nearest to each point, and maps ``[event feature, (c_q - c_cell) * (h, w), (2/H, 2/W) * (h, w), image
    feature]`` through the MLP; the four predictions are averaged with the areas of the opposite
    rectangles (bilinear-like weights).
    """

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.imnet = _PointMLP(2 * channels + 4, channels, [channels] * 3)

    def forward(self, ev_feat: Tensor, im_feat: Tensor) -> Tensor:
        """``(B, C, h, w)`` and ``(B, C, H, W)`` features -> fused ``(B, H * W, C)``."""
        b, _, height, width = im_feat.shape
        he, we = ev_feat.shape[-2:]
        device = im_feat.device
        qy, qx = _cell_centres((height, width), device)
        coord = torch.stack(torch.meshgrid(qy, qx, indexing="ij"), dim=-1).view(1, -1, 2).expand(b, -1, -1)
        ey, ex = _cell_centres((he, we), device)
        ev_coord = torch.stack(torch.meshgrid(ey, ex, indexing="ij"), dim=0)  # (2, h, w), (y, x)
        # sample the event features and their cell centres together (nearest sampling copies values)
        ev_both = torch.cat([ev_feat, ev_coord.to(ev_feat.dtype).expand(b, -1, -1, -1)], dim=1)
        ev_scale = torch.tensor([he, we], dtype=torch.float32, device=device)
        rel_cell = torch.tensor([2 / height, 2 / width], dtype=torch.float32, device=device) * ev_scale
        rel_cell = rel_cell.to(im_feat.dtype).expand(b, coord.shape[1], 2)
        eps = 1e-6
        preds, areas = [], []
        for vy in (-1, 1):  # first coordinate (rows) outer, as the official loop
            for vx in (-1, 1):
                shift = torch.tensor([vy / he + eps, vx / we + eps], dtype=torch.float64, device=device)
                pos = (coord + shift.to(coord.dtype)).clamp(-1 + 1e-6, 1 - 1e-6)
                grid = pos.flip(-1).unsqueeze(1).to(im_feat.dtype)  # grid_sample wants (x, y)
                sampled = F.grid_sample(ev_both, grid, mode="nearest", align_corners=False)[:, :, 0]
                q_ev, q_coord = sampled[:, :-2].transpose(1, 2), sampled[:, -2:].transpose(1, 2)
                q_im = F.grid_sample(im_feat, grid, mode="nearest", align_corners=False)[:, :, 0]
                q_im = q_im.transpose(1, 2)
                rel = (coord - q_coord) * ev_scale
                preds.append(self.imnet(torch.cat([q_ev, rel.to(q_ev.dtype), rel_cell, q_im], dim=-1)))
                areas.append(torch.abs(rel[..., 0] * rel[..., 1]) + 1e-9)
        total = torch.stack(areas).sum(dim=0)
        out = 0
        for pred, area in zip(preds, reversed(areas)):  # each prediction weighted by the opposite area
            out = out + pred * (area / total).unsqueeze(-1)
        return out.to(im_feat.dtype)


class _ModulatedDeformConv(nn.Module):
    """DCNv2 (modulated deformable convolution) with the offsets and masks predicted from the input.

    ``conv_offset_mask`` gives ``3 k^2`` channels, split in three: the first two thirds are the offsets
    (channel ``2j`` = dy, ``2j + 1`` = dx of kernel tap ``j``), the last third the mask logits.
    """

    def __init__(self, channels: int, kernel: int) -> None:
        super().__init__()
        self.padding = kernel // 2
        self.weight = nn.Parameter(torch.empty(channels, channels, kernel, kernel))
        self.bias = nn.Parameter(torch.empty(channels))
        self.conv_offset_mask = nn.Conv2d(channels, 3 * kernel * kernel, kernel, padding=self.padding)
        nn.init.kaiming_uniform_(self.weight, a=math.sqrt(5))
        bound = 1 / math.sqrt(channels * kernel * kernel)
        nn.init.uniform_(self.bias, -bound, bound)
        nn.init.zeros_(self.conv_offset_mask.weight)  # zero offsets, mask 0.5 at initialisation
        nn.init.zeros_(self.conv_offset_mask.bias)

    def forward(self, x: Tensor) -> Tensor:
        dy_dx_a, dy_dx_b, logits = torch.chunk(self.conv_offset_mask(x), 3, dim=1)
        offset = torch.cat([dy_dx_a, dy_dx_b], dim=1)
        mask = torch.sigmoid(logits)
        return deform_conv2d(x, offset, self.weight, self.bias, padding=self.padding, mask=mask)


class _MultiScaleFusion(nn.Module):
    """MSFF: implicit query of the event features at the image grid, then a deformable convolution."""

    def __init__(self, channels: int, kernel: int) -> None:
        super().__init__()
        self.channels = channels
        self.mlp = _ImplicitEventQuery(channels)
        self.dcn = _ModulatedDeformConv(channels, kernel)

    def forward(self, ev_feat: Tensor, im_feat: Tensor) -> Tensor:
        b, _, height, width = im_feat.shape
        fused = self.mlp(ev_feat, im_feat).view(b, height, width, self.channels).permute(0, 3, 1, 2)
        return self.dcn(fused.contiguous())


class San(nn.Module):
    """GEM's scale-aware network (SAN) with the official parameter names (``San`` in ``codes/model/san.py``).

    Args:
        im_in_channel: image channels (3).
        out_channel: output channels (3).
        ev_in_channel: event representation channels (96: EGER with 16 bins).
        initializor: ``"kaiming"`` (the released configuration) for the encoders and the decoder; the MSFF
            blocks keep PyTorch's default initialisation, their offset convolutions start at zero.

    Shape:
        - event: EGER :math:`(B, 96, h, w)` (counts, :func:`gem_eger`), with ``h, w >= 16``; any size, the
          network fuses it at the image's grid.
        - blur: blurry image :math:`(B, 3, H, W)` in [0, 1], H and W multiples of 16.
        - returns ``(L, E)``, both :math:`(B, 3, H, W)`: ``E > 0`` and ``L = blur * E`` (not clamped).

    Example:
        >>> net = San()
        >>> latent, ratio = net(torch.zeros(1, 96, 16, 16), torch.rand(1, 3, 32, 32))
        >>> latent.shape, bool((ratio > 0).all())
        (torch.Size([1, 3, 32, 32]), True)
    """

    def __init__(self, im_in_channel: int = 3, out_channel: int = 3, ev_in_channel: int = 96,
                 initializor: str = "kaiming") -> None:
        super().__init__()
        if initializor != "kaiming":
            raise ValueError(f"only initializor='kaiming' (the released configuration) is supported, "
                             f"got {initializor!r}")
        self.im_in_channel, self.out_channel, self.ev_in_channel = im_in_channel, out_channel, ev_in_channel
        # registration order = the official state_dict order
        self.im_enc = _Encoder(im_in_channel)
        self.ev_enc = _Encoder(ev_in_channel)
        self.dec = _Decoder(out_channel)
        self.msff1 = _MultiScaleFusion(16, 5)
        self.msff2 = _MultiScaleFusion(32, 3)
        self.msff3 = _MultiScaleFusion(64, 3)
        self.msff4 = _MultiScaleFusion(128, 3)
        self.msff5 = _MultiScaleFusion(128, 3)
        for part in (self.im_enc, self.dec, self.ev_enc):
            _kaiming_init(part)

    divisor = DIVISOR
    min_event_size = MIN_EVENT_SIZE

    def extra_repr(self) -> str:
        return (f"im_in_channel={self.im_in_channel}, out_channel={self.out_channel}, "
                f"ev_in_channel={self.ev_in_channel}")

    def forward(self, event: Tensor, blur: Tensor) -> tuple[Tensor, Tensor]:
        check_shape(blur, ["B", self.im_in_channel, "H", "W"], "blur")
        check_shape(event, [blur.shape[0], self.ev_in_channel, "h", "w"], "event")
        height, width = blur.shape[-2:]
        if height % DIVISOR or width % DIVISOR:
            raise ValueError(f"GEM needs the image H and W to be multiples of {DIVISOR}, got "
                             f"(H, W)=({height}, {width}); pad or crop the input")
        if min(event.shape[-2:]) < MIN_EVENT_SIZE:
            raise ValueError(f"GEM needs the event map to be at least {MIN_EVENT_SIZE}x{MIN_EVENT_SIZE}, got "
                             f"(h, w)={tuple(event.shape[-2:])}")
        blur_n = (blur - 0.5) / 0.5
        ev_feats = self.ev_enc(event)
        im_feats = self.im_enc(blur_n)
        fusions = (self.msff1, self.msff2, self.msff3, self.msff4, self.msff5)
        fused = [m(e, i) for m, e, i in zip(fusions, ev_feats, im_feats)]
        ratio = F.softplus(self.dec(fused))
        latent = (blur_n + 1) / 2 * ratio
        return latent, ratio


SAN = San  # the paper's name


# adapter ----------------------------------------------------------------------------------------
class GEMAdapter(NetworkAdapter):
    """GEM as a deblurring model on an :class:`~evlatcorr.frames.EventFrames` batch.

    Reads ``frames.corrected`` when a corrector filled it, else ``frames.events``; builds the EGER of the
    events in each exposure ``[exposure_start, exposure_end)`` with the target at mid-exposure (the
    official ``predict_ts=0.5``), or at ``frames.target_times[:, 0]`` when the batch has target times (as
    :class:`~evlatcorr.adapters.edi.EDIAdapter` does); runs the network on the blurry frame and writes
    ``L = blurry * E`` to ``output``. Grey frames (C=1) are repeated to three channels and the output is the
    mean of the three.

    Args:
        checkpoint: ``None`` (random weights), ``"default"`` (shipped weights, see
            :func:`~evlatcorr.adapters.checkpoint.resolve_checkpoint`) or a path to an official Lightning
            ``.ckpt`` (``state_dict`` with ``model.`` keys), a plain state_dict or our ``.safetensors``.
        scale_factor: image-to-event resolution ratio used to build the EGER (see :func:`gem_eger`): 1 for
            pixel-aligned events (our data; the official HS-ERGB setting), 4 to bin the events to a 4x
            coarser grid like the official Ev-REDS / MS-RBD inputs.
        num_bins: EGER time bins (16 for the released models).
        predict_ts: target time as a fraction of the exposure when ``frames.target_times`` is not set.
        clamp: clamp ``output`` to [0, 1] (the official test clamps ``L``).
        bgr: feed colour frames to the network in BGR order and return RGB (the official data are read and
            written with OpenCV). No effect on grey frames.
        pad: replicate-pad H and W up to multiples of ``16 * scale_factor`` (the EGER with zeros) and crop
            the output back (default, so any sensor size runs); when False, such sizes raise a ValueError.

    Returns (forward):
        ``frames`` with ``output`` :math:`(B, C, H, W)` (C of ``frames.blurry``).

    Example:
        >>> GEMAdapter()
        GEMAdapter(
          scale_factor=1, num_bins=16, predict_ts=0.5, clamp=True, bgr=True, pad=True
          (net): San(im_in_channel=3, out_channel=3, ev_in_channel=96)
        )
    """

    model_name = "GEM"

    def __init__(self, checkpoint: str | None = None, scale_factor: int = 1, num_bins: int = 16,
                 predict_ts: float = 0.5, clamp: bool = True, bgr: bool = True, pad: bool = True) -> None:
        super().__init__()
        check_int(scale_factor, "scale_factor")
        check_int(num_bins, "num_bins")
        if not 0.0 <= float(predict_ts) <= 1.0:
            raise ValueError(f"predict_ts must be a fraction of the exposure in [0, 1], got {predict_ts}")
        self.net = San(3, 3, SEGMENTS * 2 * num_bins)
        self.scale_factor, self.num_bins, self.predict_ts = scale_factor, num_bins, float(predict_ts)
        self.clamp, self.bgr, self.pad = clamp, bgr, pad
        self.load_checkpoint(checkpoint, "gem")

    def extra_repr(self) -> str:
        return (f"scale_factor={self.scale_factor}, num_bins={self.num_bins}, predict_ts={self.predict_ts}, "
                f"clamp={self.clamp}, bgr={self.bgr}, pad={self.pad}")

    def target_time(self, frames: EventFrames) -> Tensor:
        """The time :math:`(B,)` in µs deblurred to: ``frames.target_times[:, 0]`` or ``predict_ts`` of the
        exposure."""
        if frames.target_times is not None:
            return frames.target_times[:, 0]
        return frames.exposure_start + self.predict_ts * (frames.exposure_end - frames.exposure_start)

    @torch.compiler.disable  # events of data-dependent sizes: torch.compile compiles the network, not this
    def representation(self, frames: EventFrames) -> Tensor:
        """The network's event input: EGER :math:`(B, 96, H // s, W // s)` for the target time."""
        ts = self.target_time(frames)
        return gem_eger(self.input_events(frames), frames.exposure_start, frames.exposure_end, ts, ts,
                        self.num_bins, self.scale_factor)

    def forward(self, frames: EventFrames) -> EventFrames:
        self.check_frames(frames)
        height, width = frames.sensor_size
        s = self.scale_factor
        # padding goes to multiples of 16 s, so that the padded image and event map keep the exact ratio s;
        # without it the network needs multiples of 16
        ph, pw = self.padding(height, width, DIVISOR * s if self.pad else DIVISOR)
        if min((height + ph) // s, (width + pw) // s) < MIN_EVENT_SIZE:
            raise ValueError(f"GEM needs the event map to be at least {MIN_EVENT_SIZE}x{MIN_EVENT_SIZE}, got "
                             f"(H, W)=({height}, {width}) / scale_factor {s} = ({(height + ph) // s}, "
                             f"{(width + pw) // s}); use a larger crop or a smaller scale_factor")
        param = next(self.net.parameters())
        eger = self.representation(frames).to(param)
        colour = frames.blurry.shape[1] == 3
        x = frames.blurry.flip(1) if self.bgr and colour else rgb(frames.blurry)
        x, eger = self.pad_inputs((ph, pw), x.to(param), eger, scale=s)
        out = self.net(eger, x)[0]
        return frames.replace(output=self.finish(out.flip(1) if self.bgr and colour else out, frames))
