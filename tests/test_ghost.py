from __future__ import annotations

import math

import kornia
import pytest
import torch

from evlatcorr.config import SearchConfig
from evlatcorr.ghost import _gaussian_blur, _reflected_blur_matrix, ghost_moment, ghost_root


def test_moment_sign_follows_the_ghost():
    # the latent's log is the true image plus a ghost  −g · (θN): the moment has the ghost's sign, and the true
    # image alone (uncorrelated with N) gives about 0
    g = torch.Generator().manual_seed(0)
    sharp = torch.rand(1, 1, 32, 32, generator=g) * 0.8 + 0.1
    change = torch.randn(5, 1, 32, 32, generator=g)
    gains = torch.tensor([0.2, 0.1, 0.0, -0.1, -0.2])
    grey = sharp
    log_ratio = -gains.view(-1, 1, 1, 1) * change  # latent = grey · exp(gain · change)
    m = ghost_moment(grey, log_ratio, change)
    assert m.shape == (5,)
    assert bool((m[:-1] > m[1:]).all())  # falls with the gain
    assert m[0] > 0.3 and m[-1] < -0.3 and abs(float(m[2])) < 0.1


def test_moment_ignores_smooth_shading_shared_with_the_events():
    # a latent whose shading follows the event image's smooth part, and no fine ghost: the high-pass leaves ~0
    yy, xx = torch.meshgrid(torch.linspace(0, 1, 32), torch.linspace(0, 1, 32), indexing="ij")
    ramp = (xx + yy).view(1, 1, 32, 32)
    fine = torch.randn(1, 1, 32, 32, generator=torch.Generator().manual_seed(1))
    grey = torch.exp(ramp - 2.0)
    change = ramp + fine
    with_shading = ghost_moment(grey, torch.zeros(1, 1, 32, 32), change, sigma=1.0)
    assert abs(float(with_shading)) < 0.15
    no_high_pass = torch.corrcoef(torch.stack([ramp.flatten(), change.flatten()]))[0, 1]
    assert float(no_high_pass) > 0.1  # without the high-pass the shading alone would correlate


def test_flat_images_give_zero_not_nan():
    m = ghost_moment(torch.full((1, 1, 8, 8), 0.5), torch.zeros(2, 1, 8, 8), torch.zeros(2, 1, 8, 8))
    assert torch.equal(m, torch.zeros(2, dtype=m.dtype))


@pytest.mark.parametrize("moment, expected", [
    ([0.4, 0.2, -0.2, -0.4], 150.0),         # one fall through zero, interpolated
    ([0.4, 0.3, 0.0, -0.2], 200.0),          # zero counts as not above
    ([0.2, 0.1, 0.05, 0.01], None),          # never crosses
    ([-0.2, -0.1, 0.1, 0.2], None),          # rises through zero
    ([0.2, -0.1, 0.1, -0.2], None),          # noise: three crossings
    ([0.2, -0.1], None),                     # too few candidates
])
def test_root(moment, expected):
    lat = torch.arange(len(moment), dtype=torch.float64) * 100.0
    root = ghost_root(lat, torch.tensor(moment))
    assert root == (pytest.approx(expected) if expected is not None else None)


def test_config_bounds():
    assert SearchConfig().ghost_confidence == 0.0
    assert SearchConfig(ghost_confidence=None).ghost_confidence is None
    for bad in (-0.1, 1.5):
        with pytest.raises(ValueError, match="ghost_confidence must be in"):
            SearchConfig(ghost_confidence=bad)


@pytest.mark.parametrize("grey, log_ratio, change, sigma, match", [
    (torch.rand(1, 3, 8, 8), torch.zeros(2, 1, 8, 8), torch.zeros(2, 1, 8, 8), 1.0, r"grey must be \(1, 1, H, W\)"),
    (torch.rand(1, 1, 8, 8), torch.zeros(2, 1, 8, 7), torch.zeros(2, 1, 8, 7), 1.0, "log_ratio and log_change"),
    (torch.rand(1, 1, 8, 8), torch.zeros(2, 1, 8, 8), torch.zeros(3, 1, 8, 8), 1.0, "log_ratio and log_change"),
    (torch.rand(1, 1, 8, 8), torch.zeros(2, 1, 8, 8), torch.zeros(2, 1, 8, 8), 0.0, "sigma must be positive"),
])
def test_moment_bad_input(grey, log_ratio, change, sigma, match):
    with pytest.raises(ValueError, match=match):
        ghost_moment(grey, log_ratio, change, sigma)


def test_root_bad_input():
    with pytest.raises(ValueError, match="1-D of one length"):
        ghost_root(torch.zeros(4), torch.zeros(3))


def test_moment_from_the_inverse_ratio_equals_the_moment_from_log_r():
    from evlatcorr.ghost import inverse_ratio_moment

    g = torch.Generator().manual_seed(4)
    grey = 0.05 + 0.9 * torch.rand(1, 1, 24, 32, generator=g)
    inverse = torch.exp(0.3 * torch.randn(5, 1, 24, 32, generator=g))
    change = 0.2 * torch.randint(-3, 4, (5, 1, 24, 32), generator=g).float()
    expected = ghost_moment(grey.double(), -torch.log(inverse.double()), change.double())
    torch.testing.assert_close(inverse_ratio_moment(grey, inverse, change).double(), expected, rtol=0, atol=1e-5)


@pytest.mark.parametrize("grey, inverse, change, match", [
    (torch.rand(1, 3, 8, 8), torch.ones(2, 1, 8, 8), torch.zeros(2, 1, 8, 8), r"grey must be \(1, 1, H, W\)"),
    (torch.rand(1, 1, 8, 8), torch.ones(2, 1, 8, 7), torch.zeros(2, 1, 8, 7), "inverse and log_change"),
    (torch.rand(1, 1, 8, 8), torch.ones(2, 1, 8, 8), torch.zeros(3, 1, 8, 8), "inverse and log_change"),
])
def test_moment_from_the_inverse_ratio_bad_input(grey, inverse, change, match):
    from evlatcorr.ghost import inverse_ratio_moment

    with pytest.raises(ValueError, match=match):
        inverse_ratio_moment(grey, inverse, change)


def test_high_pass_blur_is_kornias_gaussian_blur_on_every_device(device):
    x = torch.randn(3, 1, 20, 24, generator=torch.Generator().manual_seed(4))
    want = kornia.filters.gaussian_blur2d(x, (7, 7), (1.0, 1.0))  # kornia's own CPU path
    got = _gaussian_blur(x.to(device), 1.0)
    assert got.device.type == device.type
    torch.testing.assert_close(got.cpu(), want, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("size", [(20, 24), (4, 5), (1, 1)])
def test_blur_matrices_are_kornias_reflected_gaussian_blur(size):
    # what a GPU computes (two matrix products), here in float64 on the CPU
    height, width = size
    x = torch.randn(2, 1, height, width, generator=torch.Generator().manual_seed(5), dtype=torch.float64)
    cpu = torch.device("cpu")
    if min(size) <= 3:  # fewer pixels than the radius: neither can reflect
        with pytest.raises(ValueError, match="needs at least 4 pixels"):
            _reflected_blur_matrix(min(size), 7, 1.0, cpu, torch.float64)
        return
    along_w = _reflected_blur_matrix(width, 7, 1.0, cpu, torch.float64)
    along_h = _reflected_blur_matrix(height, 7, 1.0, cpu, torch.float64)
    torch.testing.assert_close(along_h @ x @ along_w.T, kornia.filters.gaussian_blur2d(x, (7, 7), (1.0, 1.0)),
                               rtol=1e-12, atol=1e-12)


def test_stacked_moment_equals_each_frames_moment():
    from evlatcorr.ghost import inverse_ratio_moment, stacked_inverse_ratio_moment

    g = torch.Generator().manual_seed(9)
    grey = 0.2 + 0.6 * torch.rand(1, 3, 12, 14, generator=g)
    inverse = 0.5 + torch.rand(4, 3, 12, 14, generator=g)
    change = torch.randn(4, 3, 12, 14, generator=g)
    together = stacked_inverse_ratio_moment(grey, inverse, change)
    assert together.shape == (4, 3)
    for f in range(3):
        alone = inverse_ratio_moment(grey[:, f:f + 1], inverse[:, f:f + 1].contiguous(),
                                     change[:, f:f + 1].contiguous())
        torch.testing.assert_close(together[:, f], alone, rtol=1e-5, atol=1e-6)


def test_stacked_moment_refuses_shapes_that_do_not_match():
    from evlatcorr.ghost import stacked_inverse_ratio_moment

    with pytest.raises(ValueError, match=r"grey must be \(1, F, H, W\)"):
        stacked_inverse_ratio_moment(torch.rand(2, 3, 4, 4), torch.rand(5, 3, 4, 4), torch.rand(5, 3, 4, 4))
    with pytest.raises(ValueError, match="inverse and log_change both"):
        stacked_inverse_ratio_moment(torch.rand(1, 3, 4, 4), torch.rand(5, 3, 4, 4), torch.rand(5, 2, 4, 4))


def test_log_grey_floors_black_pixels_and_refuses_other_inputs():
    from evlatcorr.ghost import log_grey

    out = log_grey(torch.tensor([0.0, 0.5]), torch.float32)
    assert out.dtype == torch.float32
    torch.testing.assert_close(out, torch.tensor([math.log(1e-4), math.log(0.5)]))
    with pytest.raises(ValueError, match="floating dtype"):
        log_grey(torch.tensor([0.5]), torch.int32)
    with pytest.raises(ValueError, match="tensor"):
        log_grey([0.5], torch.float32)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("size", [(4, 5), (9, 13), (37, 41)])  # the smallest a 7-tap reflection takes, and more
def test_compiled_moment_equals_the_eager_one(monkeypatch, dtype, size):
    # a CPU correlates the high-passed images in one compiled pass; eager PyTorch blurs with kornia: the same moment
    import evlatcorr.compiled

    g = torch.Generator().manual_seed(3)
    grey = 0.2 + 0.6 * torch.rand(1, 1, *size, generator=g, dtype=dtype)
    change = torch.randn(6, 1, *size, generator=g, dtype=dtype)
    log_ratio = 0.3 * torch.randn(6, 1, *size, generator=g, dtype=dtype) - 0.2 * change * torch.arange(-3, 3).view(
        6, 1, 1, 1)
    change[5] = 1.0  # a flat event image: no correlation, 0
    monkeypatch.setattr(evlatcorr.compiled, "ENABLED", False)
    eager = ghost_moment(grey, log_ratio, change)
    monkeypatch.setattr(evlatcorr.compiled, "ENABLED", True)
    compiled = ghost_moment(grey, log_ratio, change)
    assert compiled.dtype == eager.dtype == dtype and compiled[5] == 0
    torch.testing.assert_close(compiled, eager, rtol=0, atol=1e-5 if dtype == torch.float32 else 1e-12)
    assert bool((compiled[:3] < 0).all())  # the strong ghosts read with their sign

