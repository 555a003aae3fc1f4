from __future__ import annotations

import pytest
import torch

import evlatcorr.compiled
from evlatcorr.sharpness import sharpness_scores

SCORES = ("sparsity", "sparsity_bright", "sparsity_multiscale")


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("size", [(4, 4), (5, 7), (26, 35)])  # odd sizes: the half scale drops a row and a column
def test_compiled_scores_equal_the_eager_ones(monkeypatch, dtype, size):
    # a CPU takes each log image's gradient norms at both scales in one compiled pass; eager PyTorch takes difference
    # tensors and norms: the same scores
    g = torch.Generator().manual_seed(1)
    latent = torch.rand(9, 1, *size, generator=g, dtype=dtype).cumsum(-1) + 0.05
    latent[4] = 0.5  # flat: no gradient, 0
    latency = torch.linspace(0.0, 800.0, 9, dtype=dtype)
    monkeypatch.setattr(evlatcorr.compiled, "ENABLED", False)
    eager = sharpness_scores(latent, latency, None, SCORES, 20.0, 7, 1000.0)
    monkeypatch.setattr(evlatcorr.compiled, "ENABLED", True)
    compiled = sharpness_scores(latent, latency, None, SCORES, 20.0, 7, 1000.0)
    assert compiled.shape == eager.shape == (3, 9) and compiled.dtype == eager.dtype == dtype
    torch.testing.assert_close(compiled, eager, rtol=1e-5 if dtype == torch.float32 else 1e-12, atol=1e-12)
    assert bool((compiled[:, 4] == 0).all()) and bool((compiled[:, :4] > 0).all())
    # with the temporal prior, as eager
    previous = torch.tensor(300.0, dtype=dtype)
    prior = sharpness_scores(latent, latency, previous, SCORES, 20.0, 7, 1000.0)
    monkeypatch.setattr(evlatcorr.compiled, "ENABLED", False)
    torch.testing.assert_close(prior, sharpness_scores(latent, latency, previous, SCORES, 20.0, 7, 1000.0),
                               rtol=1e-5 if dtype == torch.float32 else 1e-12, atol=1e-12)


def test_the_threads_split_the_images_and_not_the_result():
    from evlatcorr.compiled.gradients import gradient_sparsity

    image = torch.rand(11, 9, 12, generator=torch.Generator().manual_seed(2))
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = gradient_sparsity(image, True)
        torch.set_num_threads(3)
        three = gradient_sparsity(image, True)
    finally:
        torch.set_num_threads(threads)
    assert (one == three).all() and (one > 0).all()


def test_scores_keep_their_gradient_through_eager_pytorch():
    # the compiled pass is not differentiable: a latent that asks for a gradient is scored by eager PyTorch
    latent = (torch.rand(3, 1, 8, 9, generator=torch.Generator().manual_seed(4), dtype=torch.float64) + 0.1)
    latent.requires_grad_(True)
    scores = sharpness_scores(latent, torch.zeros(3, dtype=torch.float64), None, SCORES, 20.0, 7, 1000.0)
    scores.sum().backward()
    assert latent.grad is not None and bool(latent.grad.abs().sum() > 0)


def test_known_answer_of_a_ramp_and_its_half_resolution():
    from evlatcorr.compiled.gradients import gradient_sparsity

    # I[y, x] = x on 4x4: along rows 2 at the inner columns, 1 at the border ones, nothing down the columns:
    # 24 / (sqrt(40) sqrt(32)); its 2x2 means [[0.5, 2.5], [0.5, 2.5]]: 8 / (4 sqrt(8))
    ramp = torch.arange(4, dtype=torch.float64).expand(1, 4, 4).contiguous()
    full, half = gradient_sparsity(ramp, True)[:, 0]
    assert full == pytest.approx(24 / (40**0.5 * 32**0.5), rel=1e-12)
    assert half == pytest.approx(8 / (4 * 8**0.5), rel=1e-12)


@pytest.mark.parametrize(("image", "match"), [
    (torch.zeros(2, 5), "image must be a 3-D CPU tensor, got 2-D"),
    (torch.zeros(2, 5, 6).transpose(1, 2), "image must be contiguous"),
    (torch.zeros(2, 5, 6, dtype=torch.int64), "image must be one of"),
])
def test_gradient_sparsity_refuses_what_it_cannot_read(image, match):
    from evlatcorr.compiled.gradients import gradient_sparsity

    with pytest.raises(ValueError, match=match):
        gradient_sparsity(image, True)


def test_high_pass_correlation_refuses_what_it_cannot_read():
    import numpy as np

    from evlatcorr.compiled.high_pass import high_pass_correlation

    taps = np.full(7, 1 / 7)
    with pytest.raises(ValueError, match="a and b must be alike"):
        high_pass_correlation(torch.zeros(2, 5, 6), torch.zeros(2, 5, 7), taps)
    with pytest.raises(ValueError, match="at least 4 pixels"):
        high_pass_correlation(torch.zeros(2, 3, 6), torch.zeros(2, 3, 6), taps)
    with pytest.raises(ValueError, match="kernel must have 7 taps"):
        high_pass_correlation(torch.zeros(2, 5, 6), torch.zeros(2, 5, 6), taps[:5])
