from __future__ import annotations

import pytest
import torch

from evlatcorr import scenes
from evlatcorr.scenes import PROCEDURAL_SCENES, procedural_scene


@pytest.mark.parametrize("kind", PROCEDURAL_SCENES)
def test_shape_range_and_texture(kind):
    img = procedural_scene(kind, 48, 64, seed=1)
    assert img.shape == (3, 48, 64) and img.dtype == torch.float32 and img.is_contiguous()
    assert float(img.min()) >= 0.0 and float(img.max()) <= 1.0
    grey = img.mean(0)
    assert float(grey.std()) > 0.02, kind  # not flat
    # not featureless: some local structure (gradients) beyond a plane
    gx, gy = grey[:, 1:] - grey[:, :-1], grey[1:] - grey[:-1]
    assert float(gx.abs().max()) + float(gy.abs().max()) > 0.02, kind


@pytest.mark.parametrize("kind", PROCEDURAL_SCENES)
def test_seeded(kind):
    a, b = procedural_scene(kind, 40, 56, seed=7), procedural_scene(kind, 40, 56, seed=7)
    assert torch.equal(a, b)
    assert not torch.equal(a, procedural_scene(kind, 40, 56, seed=8))


@pytest.mark.parametrize("kind", PROCEDURAL_SCENES)
def test_dark_has_large_black_regions(kind):
    img = procedural_scene(kind, 64, 80, seed=3, dark=True)
    black = (img.max(0).values < 0.03).float().mean()
    assert float(black) > 0.25, (kind, float(black))
    assert float(img.max()) > 0.1  # but something is visible


def test_checkerboard_has_two_levels():
    img = procedural_scene("checkerboard", 64, 64, seed=0).mean(0)
    lo, hi = img.quantile(0.1), img.quantile(0.9)
    assert float(hi - lo) > 0.1
    middle = ((img > lo + 0.1 * (hi - lo)) & (img < hi - 0.1 * (hi - lo))).float().mean()
    assert float(middle) < 0.35  # only the antialiased edges lie between the two colours


def test_stroke_glyphs_without_fonts(monkeypatch):
    monkeypatch.setattr(scenes, "_font_path", lambda bold: None)
    a = procedural_scene("text", 48, 64, seed=2)
    b = procedural_scene("text", 48, 64, seed=2)
    assert torch.equal(a, b) and float(a.mean(0).std()) > 0.05


@pytest.mark.parametrize(
    "args, match",
    [(("plasma", 32, 32, 0), "kind"), (("text", 4, 32, 0), "height and width"), (("noise", 32, 32.5, 0), "height"),
     (("shapes", 32, 32, 1.5), "seed")],
)
def test_bad_input(args, match):
    with pytest.raises(ValueError, match=match):
        procedural_scene(*args)
