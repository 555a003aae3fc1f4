from __future__ import annotations

import pytest
import torch

from evlatcorr.continuous import ContinuousIntegral
from evlatcorr.latency_table import LatencyTable
from evlatcorr.simulate import simulate


@pytest.fixture(scope="module")
def frames():
    return simulate("camera", num_frames=2, latency="constant", latency_us=1500.0, seed=3, height=10, width=12,
                    exposure_us=4000.0).frames("delayed")


def test_entries_are_the_exact_integral_and_reads_interpolate_between_them(frames):
    table = LatencyTable.build(frames.events, frames.exposure_start, frames.exposure_end, 0.2, 0.0, 4000.0, 9)
    assert table.log_ratio.shape == (2, 9, 10, 12) and table.step == 500.0
    exact = ContinuousIntegral(frames.events.sample(1), 0.2).log_ratio(
        float(frames.exposure_start[1]), float(frames.exposure_end[1]), torch.tensor([1500.0, 2000.0]))[:, 0]
    torch.testing.assert_close(table.log_ratio[1, 3:5], exact.float())
    at_knot = table.read(torch.full((2, 1, 10, 12), 1500.0))
    halfway = table.read(torch.full((2, 1, 10, 12), 1750.0))
    torch.testing.assert_close(at_knot[1, 0], exact[0].float())
    torch.testing.assert_close(halfway[1, 0], exact.float().mean(0))


def test_read_is_differentiable_in_the_latency(frames):
    table = LatencyTable.build(frames.events, frames.exposure_start, frames.exposure_end, 0.2, 0.0, 4000.0, 9)
    table.log_ratio = table.log_ratio.double()
    # off the knots the read is linear in the latency: gradcheck's finite differences see the table's slope
    latency = (torch.rand(2, 1, 10, 12, dtype=torch.float64, generator=torch.Generator().manual_seed(0)) * 400
               + 1550.0).requires_grad_()
    assert torch.autograd.gradcheck(table.read, (latency,), eps=1e-3, atol=1e-6)
    grad = torch.autograd.grad(table.read(latency).sum(), latency)[0]
    expected = (table.log_ratio[:, 4] - table.log_ratio[:, 3]) / 500.0
    torch.testing.assert_close(grad[:, 0], expected)


def test_bad_arguments(frames):
    with pytest.raises(ValueError, match="num >= 2"):
        LatencyTable.build(frames.events, frames.exposure_start, frames.exposure_end, 0.2, 0.0, 4000.0, 1)
    with pytest.raises(ValueError, match="high > low"):
        LatencyTable.build(frames.events, frames.exposure_start, frames.exposure_end, 0.2, 100.0, 100.0, 5)
