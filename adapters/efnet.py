"""EFNet (Sun et al., "Event-Based Fusion for Motion Deblurring with Cross-modal Attention", ECCV 2022).

A re-implementation whose ``state_dict`` has the key names and shapes of the official
``basicsr/models/archs/EFNet_arch.py`` (``EFNet(wf=64, fuse_before_downsample=True)``, 8,466,445
parameters), so the released checkpoints load with ``strict=True``, plus the event representation
the released models were trained on (SCER, 6 channels, max-abs normalised, with an event mask) and
an adapter that runs it on an :class:`~evlatcorr.frames.EventFrames` batch.

Network in brief: a two-stage U-Net (depth 3, widths 64/128/256). Stage 1 fuses an event encoder into
the image encoder at every level with channel cross-attention (EICA); a supervised attention module
(SAM) gives the stage-1 image and the feature passed to stage 2; stage 2 is an image-only U-Net whose
first two levels add the stage-1 encoder/decoder features gated by the event mask (EMGC) when a mask
is given. ``forward(x, event, mask=None)`` returns ``[out_1, out_2]`` (stage 1 and the final image,
not clamped).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from evlatcorr.adapters.base import NetworkAdapter, rgb
from evlatcorr.checks import check_batch_vector, check_shape
from evlatcorr.events import Events
from evlatcorr.frames import EventFrames

__all__ = ["EFNet", "EFNetAdapter", "efnet_event_mask", "efnet_scer"]


# event representation --------------------------------------------------------------------------
def efnet_scer(events: Events, start: Tensor | float, end: Tensor | float, num_bins: int = 6,
               normalize: bool = True, span: str = "events") -> Tensor:
    """Symmetric cumulative event representation (SCER) of the events in each exposure.

    The events of sample ``b`` with ``start[b] <= t < end[b]`` are taken. With ``t0`` and ``t1`` the
    first and last of their timestamps (``span="events"``, as the official data preparation does), or
    the exposure ``start`` and ``end`` (``span="exposure"``), ``dt = t1 - t0``, ``t_mid = t0 + dt / 2``
    and the edges ``e_k = t0 + k dt / B`` (``e_B = t1``), channel ``c`` holds, per pixel:

    * ``c < B/2``: ``-(sum of polarities with e_c <= t < t_mid)`` (windows shrinking towards the middle);
    * ``c >= B/2``: ``+(sum of polarities with t_mid <= t < e_{c+1})`` (windows growing from the middle).

    So an event stamped at ``t1`` itself is in no channel (as in the official code). With ``normalize``
    each sample is divided by its largest absolute value (the official loader's ``norm_voxel``), giving
    values in [-1, 1]; a sample without events stays zero.

    Args:
        events: events with ``sensor_size`` :math:`(H, W)` and ``batch_size`` B.
        start: exposure start of each sample :math:`(B,)` in µs (or a scalar).
        end: exposure end of each sample :math:`(B,)` in µs (or a scalar).
        num_bins: number of channels, even (EFNet uses 6).
        normalize: divide each sample by its max absolute value.
        span: ``"events"`` (official) or ``"exposure"``: what ``t0`` and ``t1`` are.

    Returns:
        SCER :math:`(B, num\\_bins, H, W)` float32 on the events' device.

    Example:
        >>> ev = Events(torch.tensor([0, 1]), torch.tensor([0, 0]), torch.tensor([0.0, 60.0]),
        ...             torch.tensor([1, 1]), sensor_size=(1, 2))
        >>> efnet_scer(ev, 0.0, 100.0, normalize=False)[0, :, 0, 0].tolist()
        [-1.0, 0.0, 0.0, 0.0, 0.0, 0.0]
    """
    if not isinstance(events, Events):
        raise ValueError(f"events must be evlatcorr.Events, got {type(events).__name__}")
    if not isinstance(num_bins, int) or num_bins < 2 or num_bins % 2:
        raise ValueError(f"num_bins must be a positive even integer, got {num_bins}")
    if span not in ("events", "exposure"):
        raise ValueError(f"span must be 'events' or 'exposure', got {span!r}")
    batch_size = events.batch_size
    height, width = events.sensor_size
    device = events.device
    start = check_batch_vector(start, batch_size, "start").to(device, torch.float64)
    end = check_batch_vector(end, batch_size, "end").to(device, torch.float64)
    if bool((end <= start).any()):
        raise ValueError("end must be after start for every sample (the exposure window)")
    ev = events.window(start, end)
    out = torch.zeros(batch_size, num_bins, height, width, dtype=torch.float32, device=device)
    if len(ev) == 0:
        return out
    b, t = ev.batch, ev.t
    if span == "events":
        t0 = torch.full((batch_size,), float("inf"), dtype=torch.float64, device=device)
        t0 = t0.scatter_reduce(0, b, t, "amin")
        t1 = torch.full((batch_size,), float("-inf"), dtype=torch.float64, device=device)
        t1 = t1.scatter_reduce(0, b, t, "amax")
    else:
        t0, t1 = start, end
    dt = t1 - t0
    half = num_bins // 2
    steps = torch.arange(num_bins, device=device, dtype=torch.float64)
    edges = t0[:, None] + (dt / num_bins)[:, None] * steps  # e_0..e_{B-1} (B, num_bins), as the official code
    left = t < (t0 + dt / 2)[b]
    # left events are in channels 0..L with L = #{k in 1..half-1: e_k <= t}; right events in R..B-1 with
    # R = half + #{k in half+1..B-1: e_k <= t}; right events at or after e_B = t1 are in no channel
    first = torch.where(left, 0, half)
    for k in range(1, num_bins):
        if k != half:
            first += (t >= edges[b, k]) & (left if k < half else ~left)
    keep = left | (t < t1[b])
    index = ((b * num_bins + first) * height + ev.y) * width + ev.x
    weight = torch.where(left, -ev.p, ev.p).to(torch.float32)  # left channels hold negated sums
    hist = torch.zeros(batch_size * num_bins * height * width, dtype=torch.float32, device=device)
    hist.index_add_(0, index[keep], weight[keep])
    hist = hist.view(batch_size, num_bins, height, width)
    out[:, :half] = hist[:, :half].flip(1).cumsum(1).flip(1)  # channel c sums the bins c..half-1
    out[:, half:] = hist[:, half:].cumsum(1)  # channel c sums the bins half..c
    if normalize:
        scale = out.abs().amax(dim=(1, 2, 3), keepdim=True)
        out = torch.where(scale > 0, out / scale.clamp_min(1e-30), out)
    return out


def efnet_event_mask(voxel: Tensor) -> Tensor:
    """EFNet's event mask: pixels with a non-zero value in any channel, closed with a 3x3 square.

    Closing = dilation then erosion, with the image border ignored (OpenCV's default border for
    ``cv2.morphologyEx(..., cv2.MORPH_CLOSE, 3x3 rect)`` as the official data preparation uses, and
    kornia's ``"geodesic"`` border).

    Args:
        voxel: event representation :math:`(B, C, H, W)`.

    Returns:
        mask :math:`(B, 1, H, W)` with values in {0, 1}, same dtype as ``voxel`` (float32 for integer input).

    Example:
        >>> v = torch.zeros(1, 6, 5, 5); v[0, 0, 2, 1] = 1.0; v[0, 3, 2, 3] = -1.0  # a one-pixel gap
        >>> efnet_event_mask(v)[0, 0, 1:4].tolist()  # the gap is closed; the border does not erode
        [[0.0, 0.0, 0.0, 0.0, 0.0], [1.0, 1.0, 1.0, 1.0, 1.0], [0.0, 0.0, 0.0, 0.0, 0.0]]
    """
    check_shape(voxel, ["B", "C", "H", "W"], "voxel")
    dtype = voxel.dtype if voxel.is_floating_point() else torch.float32
    hit = (voxel != 0).any(dim=1, keepdim=True).to(dtype)
    dilated = F.max_pool2d(hit, 3, stride=1, padding=1)  # max_pool pads with -inf: border ignored
    return -F.max_pool2d(-dilated, 3, stride=1, padding=1)


# network ----------------------------------------------------------------------------------------
class _ChannelLayerNorm(nn.Module):
    """LayerNorm over the channels of a :math:`(B, C, H, W)` map (biased variance, eps 1e-5)."""

    def __init__(self, dim: int) -> None:
        super().__init__()
        self.body = nn.LayerNorm(dim, eps=1e-5)

    def forward(self, x: Tensor) -> Tensor:
        return self.body(x.permute(0, 2, 3, 1)).permute(0, 3, 1, 2)


class _CrossChannelAttention(nn.Module):
    """Multi-head channel attention with queries from the image and keys/values from the events."""

    def __init__(self, dim: int, num_heads: int) -> None:
        super().__init__()
        self.num_heads = num_heads
        self.temperature = nn.Parameter(torch.ones(num_heads, 1, 1))
        self.q = nn.Conv2d(dim, dim, 1, bias=False)
        self.k = nn.Conv2d(dim, dim, 1, bias=False)
        self.v = nn.Conv2d(dim, dim, 1, bias=False)
        self.project_out = nn.Conv2d(dim, dim, 1, bias=False)

    def forward(self, image: Tensor, event: Tensor) -> Tensor:
        b, c, h, w = image.shape
        heads = self.num_heads
        q = F.normalize(self.q(image).reshape(b, heads, c // heads, h * w), dim=-1)
        k = F.normalize(self.k(event).reshape(b, heads, c // heads, h * w), dim=-1)
        v = self.v(event).reshape(b, heads, c // heads, h * w)
        attn = torch.softmax((q @ k.transpose(-2, -1)) * self.temperature, dim=-1)
        return self.project_out((attn @ v).reshape(b, c, h, w))


class _Mlp(nn.Module):
    def __init__(self, dim: int, hidden: int) -> None:
        super().__init__()
        self.fc1 = nn.Linear(dim, hidden)
        self.act = nn.GELU()
        self.fc2 = nn.Linear(hidden, dim)

    def forward(self, x: Tensor) -> Tensor:
        return self.fc2(self.act(self.fc1(x)))


class _EventImageFusion(nn.Module):
    """EICA: image + cross attention(norm(image), norm(event)), then a token-wise MLP with a residual."""

    def __init__(self, dim: int, num_heads: int, expansion: int = 4) -> None:
        super().__init__()
        self.norm1_image = _ChannelLayerNorm(dim)
        self.norm1_event = _ChannelLayerNorm(dim)
        self.attn = _CrossChannelAttention(dim, num_heads)
        self.norm2 = nn.LayerNorm(dim)
        self.ffn = _Mlp(dim, dim * expansion)

    def forward(self, image: Tensor, event: Tensor) -> Tensor:
        fused = image + self.attn(self.norm1_image(image), self.norm1_event(event))
        tokens = fused.permute(0, 2, 3, 1)  # (B, H, W, C): the MLP acts on each pixel's channels
        tokens = tokens + self.ffn(self.norm2(tokens))
        return tokens.permute(0, 3, 1, 2)


def _conv_down(channels: int) -> nn.Conv2d:
    """Stride-2 4x4 convolution without bias: halves H and W."""
    return nn.Conv2d(channels, channels, 4, stride=2, padding=1, bias=False)


class _ResidualConv(nn.Module):
    """``lrelu(conv3x3(lrelu(conv3x3(x)))) + conv1x1(x)``; the submodules every block shares."""

    def __init__(self, in_ch: int, out_ch: int, slope: float) -> None:
        super().__init__()
        self.slope = slope
        self.identity = nn.Conv2d(in_ch, out_ch, 1)
        self.conv_1 = nn.Conv2d(in_ch, out_ch, 3, padding=1)
        self.conv_2 = nn.Conv2d(out_ch, out_ch, 3, padding=1)

    def residual(self, x: Tensor) -> Tensor:
        y = F.leaky_relu(self.conv_1(x), self.slope)
        return F.leaky_relu(self.conv_2(y), self.slope) + self.identity(x)


class _ImageBlock(_ResidualConv):
    """An image encoder/decoder level: residual convs, optional mask-gated stage-1 features (EMGC),
    optional event fusion (EICA), optional stride-2 downsampling."""

    def __init__(self, in_ch: int, out_ch: int, slope: float, downsample: bool = False, emgc: bool = False,
                 num_heads: int | None = None) -> None:
        super().__init__(in_ch, out_ch, slope)
        if emgc:
            self.emgc_enc = nn.Conv2d(out_ch, out_ch, 3, padding=1)
            self.emgc_dec = nn.Conv2d(out_ch, out_ch, 3, padding=1)
            self.emgc_enc_mask = nn.Conv2d(out_ch, out_ch, 3, padding=1)
            self.emgc_dec_mask = nn.Conv2d(out_ch, out_ch, 3, padding=1)
        self.emgc = emgc
        self.downsample = _conv_down(out_ch) if downsample else None
        if num_heads is not None:
            self.image_event_transformer = _EventImageFusion(out_ch, num_heads)
        self.fuses = num_heads is not None

    def forward(self, x: Tensor, event: Tensor | None = None, enc: Tensor | None = None,
                dec: Tensor | None = None, mask: Tensor | None = None) -> tuple[Tensor, Tensor | None]:
        """Returns ``(feature at this level, downsampled feature or None)``."""
        out = self.residual(x)
        if mask is not None and self.emgc:
            out = (out + self.emgc_enc(enc) + self.emgc_enc_mask((1 - mask) * enc)
                   + self.emgc_dec(dec) + self.emgc_dec_mask(mask * dec))
        if self.fuses:
            out = self.image_event_transformer(out, event)
        return out, (self.downsample(out) if self.downsample is not None else None)


class _EventBlock(_ResidualConv):
    """An event encoder level: returns (1x1-projected feature for fusion, downsampled raw feature or None)."""

    def __init__(self, in_ch: int, out_ch: int, slope: float, downsample: bool) -> None:
        super().__init__(in_ch, out_ch, slope)
        self.conv_before_merge = nn.Conv2d(out_ch, out_ch, 1)
        self.downsample = _conv_down(out_ch) if downsample else None

    def forward(self, x: Tensor) -> tuple[Tensor, Tensor | None]:
        out = self.residual(x)
        return self.conv_before_merge(out), (self.downsample(out) if self.downsample is not None else None)


class _UpBlock(nn.Module):
    def __init__(self, in_ch: int, out_ch: int, slope: float) -> None:
        super().__init__()
        self.up = nn.ConvTranspose2d(in_ch, out_ch, 2, stride=2)
        self.conv_block = _ImageBlock(in_ch, out_ch, slope)

    def forward(self, x: Tensor, bridge: Tensor) -> Tensor:
        return self.conv_block(torch.cat([self.up(x), bridge], dim=1))[0]


class _SupervisedAttention(nn.Module):
    """SAM (from MPRNet): a stage-1 image and an attention-gated feature for stage 2."""

    def __init__(self, dim: int, image_ch: int = 3) -> None:
        super().__init__()
        self.conv1 = nn.Conv2d(dim, dim, 3, padding=1)
        self.conv2 = nn.Conv2d(dim, image_ch, 3, padding=1)
        self.conv3 = nn.Conv2d(image_ch, dim, 3, padding=1)

    def forward(self, feature: Tensor, image: Tensor) -> tuple[Tensor, Tensor]:
        restored = self.conv2(feature) + image
        gated = self.conv1(feature) * torch.sigmoid(self.conv3(restored)) + feature
        return gated, restored


class EFNet(nn.Module):
    """EFNet with the official parameter names (``EFNet(wf=64, fuse_before_downsample=True)``).

    Args:
        in_chn: image channels (3 for the released models).
        ev_chn: event representation channels (6: SCER with 6 bins).
        wf: width of the first level (64); level ``i`` has ``wf * 2**i`` channels.
        depth: number of levels (3); H and W must be multiples of ``2**(depth - 1)``.
        fuse_before_downsample: must be True (the released configuration; the official code's other
            branch is incomplete).
        relu_slope: LeakyReLU slope.
        num_heads: attention heads of the fusion at each level.

    Shape:
        - x: blurry image :math:`(B, 3, H, W)` in [0, 1].
        - event: SCER :math:`(B, 6, H, W)` normalised to [-1, 1] (:func:`efnet_scer`).
        - mask: optional event mask :math:`(B, 1, H, W)` in {0, 1} (:func:`efnet_event_mask`).
        - returns ``[out_1, out_2]``, each :math:`(B, 3, H, W)`, not clamped; ``out_2`` is the result.

    Example:
        >>> net = EFNet(wf=8)
        >>> out_1, out_2 = net(torch.rand(1, 3, 8, 8), torch.zeros(1, 6, 8, 8))
        >>> out_2.shape
        torch.Size([1, 3, 8, 8])
    """

    def __init__(self, in_chn: int = 3, ev_chn: int = 6, wf: int = 64, depth: int = 3,
                 fuse_before_downsample: bool = True, relu_slope: float = 0.2,
                 num_heads: Sequence[int] = (1, 2, 4)) -> None:
        super().__init__()
        if not fuse_before_downsample:
            raise ValueError("only fuse_before_downsample=True (the released EFNet configuration) "
                             "is supported")
        if depth < 2 or len(num_heads) < depth:
            raise ValueError(f"depth must be >= 2 with one num_heads entry per level, got depth={depth}, "
                             f"num_heads={tuple(num_heads)}")
        self.depth, self.in_chn, self.ev_chn, self.wf = depth, in_chn, ev_chn, wf
        widths = [wf * 2**i for i in range(depth)]
        ins = [wf, *widths[:-1]]
        last = depth - 1
        # registration order = the official state_dict order
        self.down_path_1 = nn.ModuleList(
            _ImageBlock(ins[i], widths[i], relu_slope, downsample=i < last, num_heads=num_heads[i])
            for i in range(depth))
        self.down_path_2 = nn.ModuleList(
            _ImageBlock(ins[i], widths[i], relu_slope, downsample=i < last, emgc=i < last)
            for i in range(depth))
        self.conv_01 = nn.Conv2d(in_chn, wf, 3, padding=1)
        self.conv_02 = nn.Conv2d(in_chn, wf, 3, padding=1)
        self.down_path_ev = nn.ModuleList(
            _EventBlock(ins[i], widths[i], relu_slope, downsample=i < last) for i in range(depth))
        self.conv_ev1 = nn.Conv2d(ev_chn, wf, 3, padding=1)
        ups = list(reversed(range(last)))  # decoder levels, deepest first
        self.up_path_1 = nn.ModuleList(_UpBlock(widths[i + 1], widths[i], relu_slope) for i in ups)
        self.up_path_2 = nn.ModuleList(_UpBlock(widths[i + 1], widths[i], relu_slope) for i in ups)
        self.skip_conv_1 = nn.ModuleList(nn.Conv2d(widths[i], widths[i], 3, padding=1) for i in ups)
        self.skip_conv_2 = nn.ModuleList(nn.Conv2d(widths[i], widths[i], 3, padding=1) for i in ups)
        self.sam12 = _SupervisedAttention(wf, in_chn)
        self.cat12 = nn.Conv2d(2 * wf, wf, 1)
        self.last = nn.Conv2d(wf, in_chn, 3, padding=1)

    @property
    def divisor(self) -> int:
        """H and W must be multiples of this."""
        return 2 ** (self.depth - 1)

    def extra_repr(self) -> str:
        return f"in_chn={self.in_chn}, ev_chn={self.ev_chn}, wf={self.wf}, depth={self.depth}"

    def forward(self, x: Tensor, event: Tensor, mask: Tensor | None = None) -> list[Tensor]:
        check_shape(x, ["B", self.in_chn, "H", "W"], "x")
        check_shape(event, [x.shape[0], self.ev_chn, x.shape[2], x.shape[3]], "event")
        if mask is not None:
            check_shape(mask, [x.shape[0], 1, x.shape[2], x.shape[3]], "mask")
        h, w = x.shape[-2:]
        if h % self.divisor or w % self.divisor:
            raise ValueError(f"EFNet needs H and W to be multiples of {self.divisor}, got (H, W)=({h}, {w}); "
                             "pad or crop the input")
        # event encoder: the projected feature of each level is fused into the image encoder
        ev_feats = []
        e = self.conv_ev1(event)
        for block in self.down_path_ev:
            feat, down = block(e)
            ev_feats.append(feat)
            e = down if down is not None else e
        # stage 1: image encoder fused with events, decoder, SAM
        encs, masks = [], []
        x1 = self.conv_01(x)
        for i, block in enumerate(self.down_path_1):
            feat, down = block(x1, event=ev_feats[i])
            if down is None:
                x1 = feat
            else:
                encs.append(feat)
                x1 = down
                if mask is not None:
                    masks.append(F.interpolate(mask, scale_factor=0.5**i, mode="nearest"))
        decs = []
        for i, up in enumerate(self.up_path_1):
            x1 = up(x1, self.skip_conv_1[i](encs[-i - 1]))
            decs.append(x1)
        sam_feature, out_1 = self.sam12(x1, x)
        # stage 2: image-only U-Net; with a mask, the first levels add mask-gated stage-1 features
        x2 = self.cat12(torch.cat([self.conv_02(x), sam_feature], dim=1))
        skips = []
        for i, block in enumerate(self.down_path_2):
            if block.downsample is None:
                x2, _ = block(x2)
                continue
            if mask is not None:
                feat, x2 = block(x2, enc=encs[i], dec=decs[-i - 1], mask=masks[i])
            else:
                feat, x2 = block(x2)
            skips.append(feat)
        for i, up in enumerate(self.up_path_2):
            x2 = up(x2, self.skip_conv_2[i](skips[-i - 1]))
        out_2 = self.last(x2) + x
        return [out_1, out_2]


# adapter ----------------------------------------------------------------------------------------
class EFNetAdapter(NetworkAdapter):
    """EFNet as a deblurring model on an :class:`~evlatcorr.frames.EventFrames` batch.

    Reads ``frames.corrected`` when a corrector filled it, else ``frames.events``; builds the SCER of
    the events in each frame's exposure ``[exposure_start, exposure_end)`` (max-abs normalised) and, with
    ``use_mask``, the event mask, as the official GoPro/REBlur test configuration does; runs EFNet on the
    blurry frame and writes the second-stage image to ``output``. Grey frames (C=1) are repeated to RGB
    and the output converted back to grey (mean of the three channels).

    Args:
        checkpoint: ``None`` (random weights), ``"default"`` (shipped weights, see
            :func:`~evlatcorr.adapters.checkpoint.resolve_checkpoint`) or a path to an official ``.pth``
            (``{"params": ...}``), a Lightning ``.ckpt`` or our ``.safetensors``.
        use_mask: pass the event mask (enables EFNet's mask-gated stage-2 connections).
        clamp: clamp ``output`` to [0, 1] (the network output itself is not bounded).
        pad: replicate-pad H and W up to multiples of 4 and crop the output back (default, so any sensor size,
            e.g. DAVIS346's 260x346, runs); when False, such sizes raise a ValueError.

    Returns (forward):
        ``frames`` with ``output`` :math:`(B, C, H, W)` (C of ``frames.blurry``).

    Example:
        >>> EFNetAdapter()
        EFNetAdapter(
          use_mask=True, clamp=True, pad=True
          (net): EFNet(in_chn=3, ev_chn=6, wf=64, depth=3)
        )
    """

    model_name = "EFNet"
    mean_before_clamp = True  # the grey mean of the raw output, then the clamp
    num_bins = 6

    def __init__(self, checkpoint: str | None = None, use_mask: bool = True, clamp: bool = True,
                 pad: bool = True) -> None:
        super().__init__()
        self.net = EFNet(wf=64, fuse_before_downsample=True)
        self.use_mask, self.clamp, self.pad = use_mask, clamp, pad
        self.load_checkpoint(checkpoint, "efnet")

    def extra_repr(self) -> str:
        return f"use_mask={self.use_mask}, clamp={self.clamp}, pad={self.pad}"

    @torch.compiler.disable  # events of data-dependent sizes: torch.compile compiles the network, not this
    def representation(self, frames: EventFrames) -> tuple[Tensor, Tensor | None]:
        """The network's event input: SCER :math:`(B, 6, H, W)` and mask :math:`(B, 1, H, W)` (or None)."""
        voxel = efnet_scer(self.input_events(frames), frames.exposure_start, frames.exposure_end, self.num_bins,
                           normalize=True)
        mask = efnet_event_mask(voxel) if self.use_mask else None
        return voxel, mask

    def forward(self, frames: EventFrames) -> EventFrames:
        self.check_frames(frames)
        padding = self.padding(*frames.sensor_size, self.net.divisor)
        param = next(self.net.parameters())
        voxel, mask = self.representation(frames)
        x, voxel = rgb(frames.blurry).to(param), voxel.to(param)
        mask = mask.to(param) if mask is not None else None
        x, voxel, mask = self.pad_inputs(padding, x, voxel, mask)
        return frames.replace(output=self.finish(self.net(x, voxel, mask)[1], frames))
