"""REFID's network (``FinalBidirectionAttenfusion`` in AHupuJR/REFID, commit f94eb19), re-implemented with the
official ``state_dict`` key names and shapes so that the released BasicSR weights load with ``strict=True``; the
event representation, input layout, official quirks and the adapter are in :mod:`evlatcorr.adapters.refid`.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

__all__ = ["REFIDNet"]


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
