"""Procedural scenes for the simulator: text, checkerboards, shapes, gradients and noise textures.

Each scene is a seeded linear-intensity colour image :math:`(3, H, W)` in [0, 1], drawn with a
``torch.Generator`` (no global random state), so a ``(kind, size, seed)`` gives the same image on
every machine. Edges are antialiased by rendering at a higher resolution and averaging.

Pass a scene larger than the sensor (e.g. twice its size) to :func:`evlatcorr.simulate.simulate`
so the camera's path stays inside it; the simulator upsamples images that are too small.

Example:
    >>> from evlatcorr.scenes import procedural_scene
    >>> procedural_scene("shapes", 64, 80, seed=3).shape
    torch.Size([3, 64, 80])
"""

from __future__ import annotations

import math
import os
import string

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

__all__ = ["PROCEDURAL_SCENES", "procedural_scene"]

PROCEDURAL_SCENES = ("text", "checkerboard", "shapes", "gradient", "noise")
_SUPERSAMPLE = 3  # antialiasing: render at 3x and average 3x3 blocks


def procedural_scene(kind: str, height: int, width: int, seed: int, *, dark: bool = False) -> Tensor:
    """A seeded procedural scene as linear RGB :math:`(3, H, W)` in [0, 1].

    Kinds:

    - ``"text"``: lines of random characters rendered with matplotlib's bundled DejaVu fonts
      (through PIL), dark on light paper or light on dark; stroke glyphs (random line segments in
      character cells) when PIL or the fonts are missing.
    - ``"checkerboard"``: squares of a random size (4-20 px), rotation and contrast.
    - ``"shapes"``: random filled circles, rotated rectangles and convex polygons of random
      intensities and tints over a uniform or gently graded background.
    - ``"gradient"``: a smooth brightness ramp in a random direction with a few soft blobs and one
      soft edge: low texture, but not featureless.
    - ``"noise"``: band-limited noise: white noise smoothed by a Gaussian of random scale (1-6 px).

    Args:
        kind: one of :data:`PROCEDURAL_SCENES`.
        height: image height ``H`` (≥ 8); use about twice the sensor's for the simulator.
        width: image width ``W`` (≥ 8).
        seed: random seed.
        dark: make a large part of the scene black (near 0): the background of text and shapes,
            the low half of the gradient, one colour of the checkerboard, the troughs of the noise.

    Returns:
        image :math:`(3, H, W)`, float32, linear intensity in [0, 1].

    Example:
        >>> img = procedural_scene("checkerboard", 32, 48, seed=0)
        >>> img.shape, bool(img.min() >= 0), bool(img.max() <= 1)
        (torch.Size([3, 32, 48]), True, True)
    """
    if kind not in PROCEDURAL_SCENES:
        raise ValueError(f"kind must be one of {PROCEDURAL_SCENES}, got {kind!r}")
    if not isinstance(height, int) or not isinstance(width, int) or height < 8 or width < 8:
        raise ValueError(f"height and width must be integers >= 8, got {height}x{width}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)):
        raise ValueError(f"seed must be an integer, got {seed!r}")
    g = torch.Generator().manual_seed(int(seed))
    make = {"text": _text, "checkerboard": _checkerboard, "shapes": _shapes, "gradient": _gradient,
            "noise": _noise}[kind]
    return make(height, width, g, bool(dark)).float().clamp(0, 1).contiguous()


# --- helpers -------------------------------------------------------------------------------------------------------
def _uniform(g: torch.Generator, lo: float, hi: float) -> float:
    return lo + (hi - lo) * float(torch.rand((), generator=g, dtype=torch.float64))


def _randint(g: torch.Generator, lo: int, hi: int) -> int:
    """An integer in [lo, hi]."""
    return int(torch.randint(lo, hi + 1, (), generator=g))


def _tint(g: torch.Generator, level: float, amount: float = 0.25) -> Tensor:
    """An RGB colour :math:`(3,)` of roughly the given grey level with a random tint."""
    tint = 1 + amount * (2 * torch.rand(3, generator=g, dtype=torch.float64) - 1)
    return (level * tint / tint.mean()).clamp(0, 1)


def _grid(height: int, width: int, factor: int) -> tuple[Tensor, Tensor]:
    """Pixel-centre coordinates (x, y) :math:`(factor H, factor W)` of a supersampled grid, in output pixels."""
    ys = (torch.arange(height * factor, dtype=torch.float64) + 0.5) / factor - 0.5
    xs = (torch.arange(width * factor, dtype=torch.float64) + 0.5) / factor - 0.5
    y, x = torch.meshgrid(ys, xs, indexing="ij")
    return x, y


def _downsample(img: Tensor, factor: int) -> Tensor:
    """Average ``factor x factor`` blocks of :math:`(C, fH, fW)`."""
    return F.avg_pool2d(img[None], factor)[0] if factor > 1 else img


def _paint(canvas: Tensor, mask: Tensor, colour: Tensor) -> None:
    """Paint ``colour`` :math:`(3,)` where ``mask`` :math:`(H, W)` is true, in place."""
    canvas[:, mask] = colour.to(canvas)[:, None]


# --- kinds ---------------------------------------------------------------------------------------------------------
def _checkerboard(height: int, width: int, g: torch.Generator, dark: bool) -> Tensor:
    f = _SUPERSAMPLE
    x, y = _grid(height, width, f)
    size = _uniform(g, 4.0, 20.0)
    angle = _uniform(g, -math.pi / 4, math.pi / 4)
    ox, oy = _uniform(g, 0, size), _uniform(g, 0, size)
    u = (math.cos(angle) * x + math.sin(angle) * y + ox) / size
    v = (-math.sin(angle) * x + math.cos(angle) * y + oy) / size
    odd = ((torch.floor(u) + torch.floor(v)) % 2).bool()
    hi = _uniform(g, 0.5, 1.0)
    lo = _uniform(g, 0.0, 0.02) if dark else hi * (1 - _uniform(g, 0.3, 0.95))
    bright, dim = _tint(g, hi, 0.15), _tint(g, lo, 0.15)
    img = torch.where(odd[None], bright[:, None, None], dim[:, None, None])
    return _downsample(img, f)


def _shapes(height: int, width: int, g: torch.Generator, dark: bool) -> Tensor:
    f = _SUPERSAMPLE
    x, y = _grid(height, width, f)
    if dark:
        base = _tint(g, _uniform(g, 0.0, 0.02), 0.1)
        canvas = base[:, None, None].expand(3, *x.shape).clone()
    else:
        a, b = _uniform(g, 0.1, 0.8), _uniform(g, 0.1, 0.8)  # a gentle ramp across the image
        angle = _uniform(g, 0, 2 * math.pi)
        ramp = (math.cos(angle) * (x / width - 0.5) + math.sin(angle) * (y / height - 0.5)) + 0.5
        colour_a, colour_b = _tint(g, a, 0.2), _tint(g, b, 0.2)
        canvas = colour_a[:, None, None] + (colour_b - colour_a)[:, None, None] * ramp.clamp(0, 1)[None]
    side = min(height, width)
    count = _randint(g, 6, 16) if dark else _randint(g, 10, 22)
    for _ in range(count):
        kind = _randint(g, 0, 2)
        cx, cy = _uniform(g, 0, width - 1), _uniform(g, 0, height - 1)
        r = _uniform(g, 0.04, 0.16) * side
        colour = _tint(g, _uniform(g, 0.05, 1.0), 0.3)
        if kind == 0:  # circle
            mask = (x - cx) ** 2 + (y - cy) ** 2 <= r * r
        elif kind == 1:  # rotated rectangle
            angle = _uniform(g, 0, math.pi)
            half_w, half_h = r * _uniform(g, 0.6, 1.4), r * _uniform(g, 0.3, 1.0)
            u = math.cos(angle) * (x - cx) + math.sin(angle) * (y - cy)
            v = -math.sin(angle) * (x - cx) + math.cos(angle) * (y - cy)
            mask = (u.abs() <= half_w) & (v.abs() <= half_h)
        else:  # convex polygon: vertices at sorted random angles on a circle
            n = _randint(g, 3, 7)
            angles = torch.sort(torch.rand(n, generator=g, dtype=torch.float64) * 2 * math.pi).values
            px, py = cx + r * 1.3 * torch.cos(angles), cy + r * 1.3 * torch.sin(angles)
            qx, qy = torch.roll(px, -1), torch.roll(py, -1)
            # counter-clockwise in (x, y) with y down: inside is where every edge's cross product is >= 0
            cross = (qx - px)[:, None, None] * (y - py[:, None, None]) - (qy - py)[:, None, None] * (
                x - px[:, None, None])
            mask = (cross >= 0).all(0)
        _paint(canvas, mask, colour)
    return _downsample(canvas, f)


def _gradient(height: int, width: int, g: torch.Generator, dark: bool) -> Tensor:
    x, y = _grid(height, width, 1)
    angle = _uniform(g, 0, 2 * math.pi)
    ramp = (math.cos(angle) * (x - width / 2) / width + math.sin(angle) * (y - height / 2) / height) + 0.5
    if dark:  # black over about half of the frame, rising to a dim grey
        lo, hi = 0.0, _uniform(g, 0.2, 0.5)
        ramp = ((ramp - 0.5) * 2).clamp(0, 1)
    else:
        lo = _uniform(g, 0.05, 0.4)
        hi = lo + _uniform(g, 0.3, 0.55)
    colour_lo, colour_hi = _tint(g, lo, 0.2), _tint(g, hi, 0.2)
    img = colour_lo[:, None, None] + (colour_hi - colour_lo)[:, None, None] * ramp.clamp(0, 1)[None]
    side = min(height, width)
    level = torch.zeros_like(x)
    for _ in range(_randint(g, 3, 6)):  # soft blobs
        cx, cy = _uniform(g, 0, width), _uniform(g, 0, height)
        sigma = _uniform(g, 0.06, 0.2) * side
        amplitude = _uniform(g, 0.05, 0.15) * (1 if _randint(g, 0, 1) else -1)
        level = level + amplitude * torch.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * sigma**2))
    edge_angle = _uniform(g, 0, 2 * math.pi)  # one soft edge (a few px wide)
    dist = math.cos(edge_angle) * (x - _uniform(g, 0.3, 0.7) * width) + math.sin(edge_angle) * (
        y - _uniform(g, 0.3, 0.7) * height)
    level = level + _uniform(g, 0.05, 0.12) * torch.sigmoid(dist / _uniform(g, 1.5, 4.0))
    img = img * (1 + level)[None] if dark else img + level[None]
    return img


def _noise(height: int, width: int, g: torch.Generator, dark: bool) -> Tensor:
    sigma = _uniform(g, 1.0, 6.0)  # px
    white = torch.randn(4, height, width, generator=g, dtype=torch.float64)
    fy = torch.fft.fftfreq(height, dtype=torch.float64)[:, None]
    fx = torch.fft.rfftfreq(width, dtype=torch.float64)[None, :]
    gain = torch.exp(-2 * (math.pi * sigma) ** 2 * (fx**2 + fy**2))  # Gaussian blur of std sigma (periodic)
    smooth = torch.fft.irfft2(torch.fft.rfft2(white) * gain, s=(height, width))
    smooth = (smooth - smooth.mean((1, 2), keepdim=True)) / smooth.std((1, 2), keepdim=True).clamp_min(1e-12)
    luma = smooth[0] + 0.25 * smooth[1:]  # mostly grey texture, partly coloured
    contrast = _uniform(g, 0.12, 0.25)
    if dark:
        return (contrast * 1.5 * luma - 0.05).clamp_min(0)  # black troughs
    return _uniform(g, 0.35, 0.6) + contrast * luma


_CHARS = string.ascii_letters + string.digits + "  .,;:!?-+=/()&%#@"


def _font_path(bold: bool) -> str | None:
    try:
        import matplotlib
        from PIL import ImageFont  # noqa: F401
    except ImportError:
        return None
    path = os.path.join(matplotlib.get_data_path(), "fonts", "ttf", "DejaVuSans-Bold.ttf" if bold else "DejaVuSans.ttf")
    return path if os.path.isfile(path) else None


def _text(height: int, width: int, g: torch.Generator, dark: bool) -> Tensor:
    light_on_dark = dark or _randint(g, 0, 3) == 0
    paper = _uniform(g, 0.0, 0.02) if dark else (_uniform(g, 0.05, 0.2) if light_on_dark else _uniform(g, 0.6, 0.95))
    ink = _uniform(g, 0.55, 1.0) if light_on_dark else _uniform(g, 0.02, 0.25)
    bold = bool(_randint(g, 0, 1))
    path = _font_path(bold)
    coverage = _font_text(height, width, g, path) if path is not None else _stroke_text(height, width, g)
    paper_c, ink_c = _tint(g, paper, 0.15), _tint(g, ink, 0.15)
    return paper_c[:, None, None] + (ink_c - paper_c)[:, None, None] * coverage[None].to(torch.float64)


def _text_lines(height: int, width: int, g: torch.Generator) -> list[tuple[float, float, int, str]]:
    """(x, y, size px, text) of lines of random characters filling the image from top to bottom."""
    lines, y = [], _uniform(g, -4, 4)
    while y < height:
        size = _randint(g, 7, 22)
        n = int(width / (0.55 * size)) + 2
        text = "".join(_CHARS[i] for i in torch.randint(0, len(_CHARS), (n,), generator=g).tolist())
        lines.append((_uniform(g, -size, 0), y, size, text))
        y += size * _uniform(g, 1.1, 1.8)
    return lines


def _font_text(height: int, width: int, g: torch.Generator, path: str) -> Tensor:
    """Ink coverage :math:`(H, W)` in [0, 1] of text rendered with a TrueType font."""
    from PIL import Image, ImageDraw, ImageFont

    f = _SUPERSAMPLE
    image = Image.new("L", (width * f, height * f), 0)
    draw = ImageDraw.Draw(image)
    fonts: dict[int, ImageFont.FreeTypeFont] = {}
    for x, y, size, text in _text_lines(height, width, g):
        font = fonts.setdefault(size, ImageFont.truetype(path, size * f))
        draw.text((x * f, y * f), text, fill=255, font=font)
    ink = torch.from_numpy(np.asarray(image, dtype=np.float64) / 255.0)
    return _downsample(ink[None], f)[0]


def _stroke_text(height: int, width: int, g: torch.Generator) -> Tensor:
    """Ink coverage :math:`(H, W)` of stroke glyphs: 2-4 random segments per character cell (no fonts needed)."""
    starts, ends, sizes = [], [], []
    for x0, y0, size, text in _text_lines(height, width, g):
        cells = torch.tensor([i for i, c in enumerate(text) if not c.isspace()], dtype=torch.float64)
        counts = torch.randint(2, 5, (cells.numel(),), generator=g)
        cell = torch.repeat_interleave(cells, counts)
        pts = torch.rand(cell.numel(), 2, 2, generator=g, dtype=torch.float64)  # (segment, end, xy) in the cell
        pts = pts * torch.tensor([0.5 * size, 0.8 * size], dtype=torch.float64)
        pts[..., 0] += x0 + cell[:, None] * 0.6 * size
        pts[..., 1] += y0 + 0.1 * size
        starts.append(pts[:, 0])
        ends.append(pts[:, 1])
        sizes.append(size)
    f = _SUPERSAMPLE
    a, b = torch.cat(starts) * f, torch.cat(ends) * f  # in supersampled pixels
    # sample each segment every 0.5 supersampled px, mark the samples, then thicken by a max filter
    n = ((b - a).norm(dim=1) * 2).ceil().long().clamp_min(1) + 1
    seg = torch.repeat_interleave(torch.arange(n.numel()), n)
    first = torch.cumsum(n, 0) - n
    frac = (torch.arange(seg.numel()) - first[seg]).double() / (n[seg] - 1).clamp_min(1).double()
    pts = a[seg] + frac[:, None] * (b - a)[seg]
    ix, iy = pts[:, 0].round().long(), pts[:, 1].round().long()
    keep = (ix >= 0) & (ix < width * f) & (iy >= 0) & (iy < height * f)
    ink = torch.zeros(height * f, width * f, dtype=torch.float64)
    ink[iy[keep], ix[keep]] = 1.0
    stroke = 2 * round(max(1.0, 0.09 * float(np.median(sizes))) * f / 2) + 1  # odd, in supersampled px
    ink = F.max_pool2d(ink[None, None], stroke, stride=1, padding=stroke // 2)[0]
    return _downsample(ink, f)[0]
