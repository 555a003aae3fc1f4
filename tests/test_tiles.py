from __future__ import annotations

import math

import pytest
import torch

import evlatcorr.compiled
from evlatcorr.compiled.gradients import gradient_sparsity, gradient_tile_sparsity
from evlatcorr.compiled.high_pass import high_pass_correlation, high_pass_tile_correlation
from evlatcorr.ghost import inverse_ratio_moment
from evlatcorr.image_tiles import check_grid, tile_counts, tile_edges, tile_pixels, tile_sums
from evlatcorr.overshoot import overshoot
from evlatcorr.sharpness import _gradient_sparsity
from evlatcorr.tile_curves import (
    _tile_upper_quantiles,
    tile_gradient_sparsity,
    tile_moments,
    tile_overshoots,
    tile_sparsity_scores,
)
from evlatcorr.tile_reader import NUM_TILE_FEATURES, load_tile_reader, tile_inputs, tile_log_probability


def _images(k: int, height: int, width: int, seed: int = 0, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.rand(k, 1, height, width, generator=g, dtype=dtype).cumsum(-1) + 0.05


def test_tiles_partition_the_image():
    assert tile_edges(10, 3) == [0, 3, 7, 10]
    counts = tile_counts(10, 7, (3, 2))
    assert counts.tolist() == [12.0, 9.0, 16.0, 12.0, 12.0, 9.0] and counts.sum() == 70  # rows 3, 4, 3; columns 4, 3
    values = torch.arange(70.0).view(10, 7)
    sums = tile_sums(values, (3, 2))
    assert sums.shape == (6,) and sums.sum() == values.sum()
    assert sums[0] == values[:3, :4].sum() and sums[5] == values[7:, 4:].sum()
    with pytest.raises(ValueError, match="grid must be"):
        check_grid((4, 1), 3, 8)
    with pytest.raises(ValueError, match="grid must be"):
        tile_sums(values, (2, 0))


def test_tile_sums_accumulate_in_the_dtype_asked_and_read_integers():
    values = torch.full((2, 300, 200), 0.1, dtype=torch.float32)  # 10000 values a tile: float32 sums are off by ~1e-7
    sums = tile_sums(values, (3, 2), torch.float64)
    assert sums.dtype == torch.float64 and sums.shape == (2, 6)
    torch.testing.assert_close(sums, torch.full((2, 6), 10000 * float(values[0, 0, 0]), dtype=torch.float64),
                               rtol=1e-12, atol=0)
    assert tile_sums(torch.ones(4, 6, dtype=torch.int64), (2, 3)).tolist() == [4.0] * 6


def test_tile_pixels_list_each_tile_s_pixels_padded_past_the_last():
    pixels = tile_pixels(10, 7, (3, 2))
    counts = tile_counts(10, 7, (3, 2)).long()
    assert pixels.shape == (6, int(counts.max()))
    image = torch.arange(70).view(10, 7)
    for t, (rows, cols) in enumerate([(r, c) for r in ((0, 3), (3, 7), (7, 10)) for c in ((0, 4), (4, 7))]):
        own = pixels[t][pixels[t] < 70]
        assert len(own) == counts[t] and own.tolist() == image[rows[0]:rows[1], cols[0]:cols[1]].flatten().tolist()
        assert bool((pixels[t, counts[t]:] == 70).all())
    with pytest.raises(ValueError, match="grid must be"):
        tile_pixels(4, 4, (5, 1))  # more tile rows than pixel rows


@pytest.mark.parametrize("q", [0.99, 0.5, 1.0])
def test_tile_quantiles_from_one_gather_equal_the_tiles_one_by_one(q):
    # a GPU takes the gather; the CPU's slices are the reference. Tiles of 20-36 pixels and of one.
    values = torch.randn(3, 2, 17, 19, generator=torch.Generator().manual_seed(0))
    for grid in ((3, 3), (2, 4), (17, 19)):
        sliced = _tile_upper_quantiles(values, grid, q, gather=False)
        gathered = _tile_upper_quantiles(values, grid, q, gather=True)
        assert sliced.shape == (3, 2, grid[0] * grid[1])
        torch.testing.assert_close(gathered, sliced, rtol=0, atol=0)
    torch.testing.assert_close(_tile_upper_quantiles(values, (17, 19), q, gather=True), values.flatten(-2))


@pytest.mark.parametrize("size", [(12, 12), (26, 35), (31, 17)])
def test_compiled_tile_sparsity_equals_eager_and_its_whole_the_shipped_score(monkeypatch, size):
    log = _images(5, *size).log()
    log[2] = 0.3  # flat: every tile 0
    compiled = tile_gradient_sparsity(log, True, (3, 3))
    monkeypatch.setattr(evlatcorr.compiled, "ENABLED", False)
    eager = tile_gradient_sparsity(log, True, (3, 3))
    assert compiled.shape == eager.shape == (2, 5, 10)
    torch.testing.assert_close(compiled, eager, rtol=1e-10, atol=1e-12)
    assert bool((compiled[:, 2] == 0).all()) and bool((compiled[:, [0, 1, 3, 4]] > 0).all())
    # images asking for a gradient take the functional differences: the same values, and a gradient back
    asking = log.clone().requires_grad_()
    graded = tile_gradient_sparsity(asking, True, (3, 3))
    torch.testing.assert_close(graded.detach(), eager, rtol=1e-12, atol=1e-14)
    graded[0].sum().backward()
    assert asking.grad is not None and bool(asking.grad[[0, 1, 3, 4]].isfinite().all())  # a flat image has none
    # the whole image's column is the score the search takes, at full and half resolution
    torch.testing.assert_close(compiled[0, :, 0], _gradient_sparsity(log).double(), rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(compiled[:, :, 0], torch.from_numpy(gradient_sparsity(log[:, 0].contiguous(), True)),
                               rtol=1e-12, atol=0)


def test_eager_tile_sparsity_of_float32_images_sums_as_the_compiled_pass_and_reads_one_pixel_sides(monkeypatch):
    log = _images(4, 40, 52, dtype=torch.float32).log()
    compiled = tile_gradient_sparsity(log, True, (3, 3))
    monkeypatch.setattr(evlatcorr.compiled, "ENABLED", False)
    torch.testing.assert_close(tile_gradient_sparsity(log, True, (3, 3)), compiled, rtol=1e-10, atol=1e-12)
    column = _images(3, 9, 1).log()  # (3, 1, 9, 1): no x differences; transposed, no y differences
    for image in (column, column.transpose(-1, -2)):
        out = tile_gradient_sparsity(image, False, (1, 1))
        torch.testing.assert_close(out[0, :, 0], _gradient_sparsity(image).double(), rtol=1e-10, atol=1e-12)


def test_a_tile_s_sparsity_reads_the_differences_at_its_own_pixels():
    # texture in the right third only: the left and middle tiles see flat pixels (0) but the middle column's
    # differences at its right edge reach into the texture; each tile's ratio is over its own pixels
    image = torch.zeros(1, 1, 9, 9, dtype=torch.float64)
    image[..., 6:] = torch.rand(1, 1, 9, 3, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    tiles = tile_gradient_sparsity(image, False, (3, 3))[0, 0, 1:].view(3, 3)
    assert bool((tiles[:, 0] == 0).all()) and bool((tiles[:, 1] > 0).all()) and bool((tiles[:, 2] > 0).all())
    only_right = image[..., :, 6:]  # the right tiles' own sums: their pixels, with the left neighbours' differences
    assert tiles[1, 2] != _gradient_sparsity(only_right[..., 3:6, :]).item()  # not a crop: the border reads across


@pytest.mark.parametrize("size", [(12, 15), (27, 40)])
def test_compiled_tile_moments_equal_eager_and_the_whole_is_the_shipped_moment(monkeypatch, size):
    g = torch.Generator().manual_seed(5)
    grey = 0.2 + 0.6 * torch.rand(1, 1, *size, generator=g)
    inverse = torch.exp(0.3 * torch.randn(4, 1, *size, generator=g))
    change = torch.randn(4, 1, *size, generator=g)
    compiled = tile_moments(grey, inverse, change, (3, 3))
    monkeypatch.setattr(evlatcorr.compiled, "ENABLED", False)
    eager = tile_moments(grey, inverse, change, (3, 3))
    assert compiled.shape == eager.shape == (4, 1, 10)
    torch.testing.assert_close(compiled, eager, rtol=1e-4, atol=1e-5)  # float32 images
    asking = inverse.clone().requires_grad_()  # the functional high-pass: the same values, and a gradient back
    graded = tile_moments(grey, asking, change, (3, 3))
    torch.testing.assert_close(graded.detach(), eager)
    graded.sum().backward()
    assert asking.grad is not None and bool(asking.grad.isfinite().all())
    torch.testing.assert_close(compiled[:, 0, 0], inverse_ratio_moment(grey, inverse, change).double(), rtol=1e-5,
                               atol=1e-6)
    assert bool((compiled.abs() <= 1).all())


def test_compiled_tile_correlation_of_the_whole_grid_is_the_shipped_one_to_the_bit():
    import numpy as np

    a, b = _images(3, 9, 11, 1)[:, 0], _images(3, 9, 11, 2)[:, 0]
    taps = np.array([0.004, 0.054, 0.242, 0.4, 0.242, 0.054, 0.004])
    one = high_pass_tile_correlation(a, b, taps, (1, 1))
    assert one.shape == (3, 1) and (one[:, 0] == high_pass_correlation(a, b, taps)).all()
    assert high_pass_tile_correlation(a, b, taps, (3, 2)).shape == (3, 7)
    assert gradient_tile_sparsity(a, True, (1, 1)).shape == (2, 3, 1)


def test_tile_overshoots_whole_is_the_shipped_overshoot_and_tiles_read_their_own_pixels():
    grey = torch.full((1, 1, 12, 12), 0.5)
    inverse = torch.ones(2, 1, 12, 12)
    peak = torch.zeros(2, 1, 12, 12)
    peak[1, 0, :4, :4] = math.log(4.0)  # the top-left tile's latent is 4x brighter than the frame
    out = tile_overshoots(grey, inverse, peak, (3, 3))
    torch.testing.assert_close(out[:, 0, 0], overshoot(grey, inverse, peak))
    assert out[1, 0, 1] == pytest.approx(math.log(4.0), rel=1e-5) and bool((out[1, 0, 2:] == 0).all())
    assert bool((out[0] == 0).all())


def test_tile_scores_of_several_frames_are_each_frame_s_own():
    g = torch.Generator().manual_seed(7)
    grey = 0.1 + 0.8 * torch.rand(1, 2, 18, 18, generator=g)
    inverse = torch.exp(0.2 * torch.randn(3, 2, 18, 18, generator=g))
    both = tile_sparsity_scores(grey, inverse)
    for f in range(2):
        alone = tile_sparsity_scores(grey[:, f:f + 1], inverse[:, f:f + 1].contiguous())
        torch.testing.assert_close(both[:, :, f], alone[:, :, 0])
    assert both.shape == (3, 3, 2, 10)


def test_tile_reader_reads_the_whole_frame_s_rows_and_the_tiles_summary():
    k = 13
    whole = torch.randn(2, NUM_TILE_FEATURES - 2, k)
    valid = torch.ones(2, k, dtype=torch.bool)
    valid[1, 10:] = False
    tile_log_p = torch.log_softmax(torch.randn(2, 9, k), -1)
    share = torch.softmax(torch.randn(2, 9), -1)
    inputs = tile_inputs(whole, tile_log_p, share, valid)
    assert inputs.shape == (2, NUM_TILE_FEATURES, k)
    torch.testing.assert_close(inputs[:, :5], whole[:, :5])
    torch.testing.assert_close(inputs[:, -1], whole[:, -1])
    torch.testing.assert_close(inputs[0, 6], tile_log_p[0].amax(0) / 10)
    assert bool((inputs[1, 5:7, 10:] == 0).all())  # nothing where a candidate is not valid
    log_p = tile_log_probability(inputs, torch.randn(2, k), valid)
    assert log_p.dtype == torch.float64 and bool(torch.isinf(log_p[1, 10:]).all())
    mass = log_p.exp().sum(1)  # the mean of two normalised log-probabilities: a geometric mean, at most 1
    assert bool((mass > 0).all()) and bool((mass <= 1 + 1e-12).all())
    with pytest.raises(ValueError, match="need whole"):
        tile_inputs(whole, tile_log_p[:, :, :5], share, valid)


def test_the_tile_reader_refuses_the_curve_reader_s_weights(tmp_path):
    from evlatcorr.locations import checkpoint_dirs

    shipped = next(f for f in (d / "curve-reader.safetensors" for d in checkpoint_dirs()) if f.is_file())
    with pytest.raises(ValueError, match="not the tile reader's 8"):
        load_tile_reader(str(shipped))
    with pytest.raises(FileNotFoundError, match="no tile reader weights"):
        load_tile_reader(str(tmp_path / "none.safetensors"))
    assert next(load_tile_reader().parameters()).shape[1] == NUM_TILE_FEATURES


def test_the_default_search_takes_the_centre_of_the_tile_reader_s_probability():
    from evlatcorr.benchmark.accuracy import make_cases, simulate_case
    from evlatcorr.config import SearchConfig
    from evlatcorr.curve_reader import load_curve_reader, probability_centre
    from evlatcorr.search import search_constant_latency
    from evlatcorr.tile_curves import candidate_tile_curves
    from evlatcorr.tile_reader import read_tiles

    case = next(c for c in make_cases("dev") if c.name.startswith("dev-17-"))  # text translating, 10.86 ms
    frames = simulate_case(case)[0]
    args = (frames.blurry, frames.events, frames.exposure_start, frames.exposure_end, case.threshold)
    assert SearchConfig().tiles
    default, whole = search_constant_latency(*args), search_constant_latency(*args, tiles=False)
    assert default.source == whole.source == ["reader"]
    # what the search does, step by step: the tiles' curves, the curve reader on each, the tile reader, the centre
    candidates, (curves, tiles, share, valid) = candidate_tile_curves(
        frames.blurry, frames.events, float(frames.exposure_start[0]), float(frames.exposure_end[0]), case.threshold)
    whole_log_p = load_curve_reader()(curves[None], valid[None])
    inputs = tile_inputs(curves[None], read_tiles(tiles[None], valid[None]), share[None], valid[None])
    log_p = tile_log_probability(inputs, whole_log_p, valid[None])[0]
    _, centre = probability_centre(log_p, candidates.double(), int(valid.sum()))
    assert default.latency.item() == pytest.approx(centre, abs=0.5)
    assert abs(default.latency.item() - case.latency_us) < 500.0 and default.latency.item() != whole.latency.item()


def test_tile_functions_refuse_shapes_they_cannot_read():
    from evlatcorr.tile_reader import read_tiles

    grey, inverse = torch.rand(1, 1, 18, 18), torch.rand(4, 1, 18, 18) + 0.5
    with pytest.raises(ValueError, match="size and parts must be positive"):
        tile_edges(10, 0)
    with pytest.raises(ValueError, match="log must be"):
        tile_gradient_sparsity(inverse[:, 0], False)
    with pytest.raises(ValueError, match="grey must be"):
        tile_sparsity_scores(grey[0], inverse)
    with pytest.raises(ValueError, match="grey must be"):
        tile_moments(grey, inverse, torch.rand(3, 1, 18, 18))
    with pytest.raises(ValueError, match="log_peak must be"):
        tile_overshoots(grey, inverse, torch.zeros(4, 1, 9, 9))
    with pytest.raises(ValueError, match="grid must be"):
        tile_counts(4, 4, (5, 1))
    with pytest.raises(ValueError, match="need tiles"):
        read_tiles(torch.zeros(2, 9, 6), torch.ones(2, 6, dtype=torch.bool))
    with pytest.raises(ValueError, match="need inputs"):
        valid = torch.ones(2, 7, dtype=torch.bool)
        tile_log_probability(torch.zeros(2, NUM_TILE_FEATURES - 1, 7), torch.zeros(2, 7), valid)
