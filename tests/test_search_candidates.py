from __future__ import annotations

import torch

from evlatcorr.config import SearchConfig
from evlatcorr.search_candidates import _SCORE_CHUNK, _aligned_candidates, _latent_scores, _score_chunk
from evlatcorr.sharpness import sharpness_scores


def test_scores_of_the_inverse_ratio_equal_the_scores_of_the_latent_images():
    # the search scores grey · (1 / R) without making the latents: the same values as sharpness_scores
    g = torch.Generator().manual_seed(6)
    grey = torch.rand(1, 1, 20, 24, generator=g)
    inverse = torch.exp(0.5 * torch.randn(6, 1, 20, 24, generator=g))
    latency, names = torch.linspace(0.0, 5000.0, 6), ("sparsity", "sparsity_bright", "sparsity_multiscale", "etf")
    config = SearchConfig()
    for previous in (None, torch.full((6,), 1000.0)):
        expected = sharpness_scores(grey * inverse, latency, previous, names, config.epsilon, config.window,
                                    config.sigma_us)
        torch.testing.assert_close(_latent_scores(grey, inverse, latency, previous, names, config), expected,
                                   rtol=1e-5, atol=0)


def test_score_chunk_fills_a_device_budget(monkeypatch):
    import evlatcorr.compiled

    # a CPU: every DAVIS346 candidate at once for the compiled passes (64 MB of one image each), 16 for eager PyTorch
    assert _score_chunk(torch.zeros(1, 1, 260, 346)) == 2**26 // (4 * 260 * 346)  # 186 candidates
    assert _score_chunk(torch.zeros(1, 1, 2**12, 2**12)) == _SCORE_CHUNK
    monkeypatch.setattr(evlatcorr.compiled, "ENABLED", False)
    assert _score_chunk(torch.zeros(1, 1, 260, 346)) == _SCORE_CHUNK
    on_device = torch.zeros(1, 1, 260, 346, device="meta")  # a device other than the CPU, with no memory
    assert _score_chunk(on_device) == 2**30 // (8 * 4 * 260 * 346)  # 372 candidates
    assert _score_chunk(torch.zeros(1, 1, 2**14, 2**14, device="meta")) == 1


def test_aligned_candidates_share_window_ends_and_cover_the_range():
    # 0-20 ms over a 20 ms exposure: 101 candidates 200 us apart, so a window's end and its mid-exposure reference
    # fall on other candidates' window starts
    coarse, step = _aligned_candidates(0.0, 20000.0, 101, 20000.0)
    assert step == 200.0 and len(coarse) == 101 and float(coarse[-1]) == 20000.0
    assert set((coarse[coarse <= 10000.0] + 10000.0).tolist()) <= set(coarse.tolist())
    # 0-15 ms: the spacing divides half the exposure (10 ms / 67), and the range's end is added as a last candidate
    coarse, step = _aligned_candidates(0.0, 15000.0, 101, 20000.0)
    assert step == 10000.0 / 67 and float(coarse[-1]) == 15000.0 and float(coarse[-2]) == 100 * step
    # an empty range: its two ends
    coarse, step = _aligned_candidates(300.0, 300.0, 101, 20000.0)
    assert coarse.tolist() == [300.0, 300.0] and step == 0.0
