"""The corrector gives the same answers on every device (CPU always; CUDA where present).

Each test computes a reference on the CPU and compares the ``device`` fixture's result with it, plus a known
answer, so on a CPU-only machine they still check the answer and that two runs agree.
"""

from __future__ import annotations

import pytest
import torch

from evlatcorr import EventLatencyCorrector
from evlatcorr.continuous import ContinuousIntegral
from evlatcorr.simulate import simulate

LATENCY_US = 3000.0


@pytest.fixture(scope="module")
def delayed():
    """One 20 ms frame of a translating photograph whose events are 3 ms late."""
    seq = simulate("astronaut", num_frames=1, latency="constant", latency_us=LATENCY_US, seed=0,
                   height=96, width=128)
    return seq.frames("delayed")


def test_continuous_reads_match_the_cpu(device, delayed):
    events = delayed.events
    start, end = float(delayed.exposure_start[0]), float(delayed.exposure_end[0])
    latencies = torch.linspace(0.0, 12_000.0, 37, dtype=torch.float64)
    on_cpu = ContinuousIntegral(events, 0.2)
    on_device = ContinuousIntegral(events.to(device), 0.2)
    inverse = on_device.inverse_ratio(start, end, latencies.to(device))
    assert inverse.device.type == device.type and inverse.dtype == torch.float32
    torch.testing.assert_close(inverse.cpu(), on_cpu.inverse_ratio(start, end, latencies), rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(on_device.log_ratio(start, end, latencies.to(device)).cpu(),
                               on_cpu.log_ratio(start, end, latencies), rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(on_device.log_change(start, end, latencies.to(device)).cpu(),
                               on_cpu.log_change(start, end, latencies), rtol=1e-9, atol=1e-9)


def test_constant_corrector_matches_the_cpu(device, delayed):
    corrector = EventLatencyCorrector()
    reference = corrector(delayed)
    out = corrector(delayed.to(device))
    assert out.latency.device.type == device.type
    # the learned reader and the scores run in float32: a device may order two near-equal candidates
    # differently, so allow one candidate step (about 120 us here)
    assert float(out.latency.mean()) == pytest.approx(float(reference.latency.mean()), abs=150.0)
    assert abs(float(out.latency.mean()) - LATENCY_US) < 1000.0
    torch.testing.assert_close(out.latent.cpu(), reference.latent, rtol=0, atol=0.05)


def test_spatial_corrector_matches_the_cpu(device, delayed):
    corrector = EventLatencyCorrector(mode="spatial", steps=10)
    reference = corrector(delayed)
    out = corrector(delayed.to(device))
    assert out.latency.device.type == device.type and out.latency.shape == reference.latency.shape
    torch.testing.assert_close(out.latency.cpu(), reference.latency, rtol=0, atol=150.0)
    assert (out.latency.median() - LATENCY_US).abs().item() < 1500.0


def test_curve_reader_inputs_and_pick_stay_on_the_device(device):
    from evlatcorr.curve_reader import curve_features
    from evlatcorr.search_learned import _curve_reader_on

    generator = torch.Generator().manual_seed(0)
    scores = torch.rand(3, 101, generator=generator, dtype=torch.float64)
    valid = torch.arange(101) < 80
    scores[:, ~valid] = float("inf")
    moment = torch.randn(101, generator=generator, dtype=torch.float64)
    overshoot = torch.rand(101, generator=generator, dtype=torch.float64)
    on_cpu = curve_features(scores, moment, valid, overshoot)
    on_device = curve_features(scores.to(device), moment.to(device), valid.to(device), overshoot.to(device))
    assert on_device.device.type == device.type
    torch.testing.assert_close(on_device.cpu(), on_cpu, rtol=0, atol=0)
    assert float(on_cpu[0, valid].median()) == 0.0  # each curve relative to its median over the valid candidates
    ensemble = _curve_reader_on(torch.device(device))
    with torch.no_grad():  # as the search calls it (an earlier test may have loaded it in inference mode)
        log_p = ensemble(on_device[None].to(next(ensemble.parameters()).dtype), valid[None].to(device))[0]
        reference = _curve_reader_on(torch.device("cpu"))(on_cpu[None], valid[None])[0]
    torch.testing.assert_close(log_p.cpu().float(), reference, rtol=1e-4, atol=1e-4)
    assert int(log_p.argmax()) == int(reference.argmax()) < 80  # never an invalid candidate


def test_tile_reductions_match_the_cpu(device):
    # a GPU takes the eager sums (column sums and a matrix product, one gather for the tiles' quantiles) where a CPU
    # takes its compiled passes and slices
    from evlatcorr.overshoot import overshoot_stride
    from evlatcorr.tile_curves import tile_moments, tile_overshoots, tile_sparsity_scores

    generator = torch.Generator().manual_seed(3)
    grey = 0.2 + 0.6 * torch.rand(1, 2, 40, 52, generator=generator)
    inverse = torch.exp(0.3 * torch.randn(6, 2, 40, 52, generator=generator))
    change = torch.randn(6, 2, 40, 52, generator=generator)
    stride = overshoot_stride(40, 52)
    peak = 0.1 * torch.rand(6, 2, -(-40 // stride), -(-52 // stride), generator=generator)
    on_device = [x.to(device) for x in (grey, inverse, change, peak)]
    pairs = [(tile_sparsity_scores(grey, inverse), tile_sparsity_scores(*on_device[:2]), 1e-7),
             (tile_moments(grey, inverse, change), tile_moments(*on_device[:3]), 1e-4),
             (tile_overshoots(grey, inverse, peak), tile_overshoots(*on_device[:2], on_device[3]), 1e-5)]
    for reference, out, tolerance in pairs:
        assert out.device.type == device.type and out.shape == reference.shape and out.shape[-1] == 10
        torch.testing.assert_close(out.cpu(), reference, rtol=tolerance, atol=tolerance)


def test_a_stream_batch_with_a_still_frame_stays_on_the_device(device):
    # the still frame's outputs are made by the stream, the moving one's by the corrector: torch.cat puts them back
    # together, so both must be on the device
    import warnings

    from evlatcorr.frames import EventFrames
    from evlatcorr.temporal import StreamingLatencyCorrector

    moving = simulate("camera", num_frames=2, height=32, width=48, latency_us=LATENCY_US, seed=0).frames("delayed")
    first, second = moving.split()
    ev = first.events  # its events moved before its exposure: still
    still = first.replace(events=type(ev)(ev.x, ev.y, ev.t - 3 * float(first.exposure_time[0]), ev.p,
                                          sensor_size=ev.sensor_size))
    batch = EventFrames.cat([still, second])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        reference = StreamingLatencyCorrector(threshold=0.2)(batch)
        out = StreamingLatencyCorrector(threshold=0.2)(batch.to(device))
    assert out.meta["latency_source"] == ["no events", "reader"]
    for key, value in out.meta.items():
        if isinstance(value, torch.Tensor):
            assert value.device.type == device.type, key
    torch.testing.assert_close(out.latency.flatten(1).mean(1).cpu(), reference.latency.flatten(1).mean(1),
                               rtol=0, atol=150.0)
