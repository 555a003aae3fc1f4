from __future__ import annotations

import pytest
import torch

from evlatcorr.blank_frames import (
    MIN_STRUCTURE_RATIO,
    blank_codes,
    blank_kinds,
    blank_pairs,
    structure_ratio,
    unclipped_share,
)


def _scene(noise: float = 0.0, seed: int = 0) -> torch.Tensor:
    """A smooth blob on a ramp, 48x64, with white noise of ``noise``."""
    g = torch.Generator().manual_seed(seed)
    yy, xx = torch.meshgrid(torch.linspace(-1, 1, 48), torch.linspace(-1, 1, 64), indexing="ij")
    image = 0.3 + 0.1 * xx + 0.3 * torch.exp(-(xx**2 + yy**2) / 0.1)
    return (image + noise * torch.randn(48, 64, generator=g)).clamp(0, 1)[None, None]


def test_unclipped_share_counts_the_pixels_inside_the_range_and_refuses_other_shapes():
    frame = torch.zeros(2, 3, 10, 10)
    frame[0, :, :2] = 0.5  # 20 of 100 pixels of grey inside the range
    frame[1] = 1.0  # saturated
    torch.testing.assert_close(unclipped_share(frame), torch.tensor([0.2, 0.0]))
    with pytest.raises(ValueError, match=r"images must be a \(B, C, H, W\) tensor"):
        unclipped_share(torch.zeros(10, 10))
    with pytest.raises(ValueError, match=r"images must be a \(B, C, H, W\) tensor"):
        structure_ratio(torch.zeros(10, 10))


@pytest.mark.parametrize("level", [0.02, 0.5])
@pytest.mark.parametrize("sigma", [0.003, 0.02])
def test_a_uniform_frame_with_noise_is_flat_and_a_scene_under_the_same_noise_is_not(level, sigma):
    g = torch.Generator().manual_seed(1)
    uniform = (level + sigma * torch.randn(1, 1, 48, 64, generator=g)).clamp(0, 1)
    ratio = structure_ratio(torch.cat([uniform, _scene(sigma)]))
    assert ratio[0] < 1.5 < MIN_STRUCTURE_RATIO  # white noise: about 1 whatever its level
    assert ratio[1] > 5 * MIN_STRUCTURE_RATIO


def test_structure_ratio_values():
    exact = torch.full((1, 1, 16, 16), 0.4)
    assert structure_ratio(exact).tolist() == [0.0]  # no variation at all
    # no noise: the neighbours' steps are the scene's own gradient, and its structure stands far above them
    assert structure_ratio(_scene()).item() > 30 * MIN_STRUCTURE_RATIO
    # three channels are read as grey, whatever the layout in memory
    colour = _scene(0.01).expand(1, 3, 48, 64)
    torch.testing.assert_close(structure_ratio(colour), structure_ratio(_scene(0.01)), rtol=1e-5, atol=0)
    torch.testing.assert_close(structure_ratio(colour.transpose(2, 3).contiguous().transpose(2, 3)),
                               structure_ratio(colour))


def test_blank_codes_kinds_and_pairs():
    frames = torch.cat([torch.zeros(1, 1, 48, 64), torch.full((1, 1, 48, 64), 0.5), _scene(0.01),
                        torch.ones(1, 1, 48, 64)])
    assert blank_codes(frames).tolist() == [1, 2, 0, 1]  # black, flat, a scene, saturated (clipped before flat)
    assert blank_kinds(frames) == ["clipped", "flat", None, "clipped"]
    assert blank_pairs(frames[:2], frames[2:]).tolist() == [True, True]
    assert blank_pairs(frames[2:3], frames[2:3]).tolist() == [False]
