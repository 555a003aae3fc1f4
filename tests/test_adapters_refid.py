from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from evlatcorr import EventFrames, Events
from evlatcorr.adapters.refid import (
    REFIDAdapter,
    REFIDNet,
    nearest_frames,
    refid_inputs,
    refid_output_times,
    refid_voxel_grid,
    refid_window,
)
from tests.conftest import random_events

# outputs of the official code (AHupuJR/REFID f94eb19, CPU fp32) for synthetic_state(seed=0) and golden_inputs();
# a variant passing each frame its own backward state (no list aliasing) differs by up to 0.21 on frames 1..3
SUMS = [-9.77153, -12.14762, -13.70899, -14.36085]
ABSSUMS = [35.90385, 39.5009, 39.41952, 40.4767]
PIXELS = [-0.192071, 0.187467, 0.143106, -0.294174, 0.19999, 0.059157, -0.231722, 0.16933, 0.064681, -0.246778,
          0.141483, 0.11719]  # y[0, :, :, 3, 5]


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    """Tiny convolutions: one thread is much faster than two when other jobs share the cores."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def synthetic_state(state: dict[str, torch.Tensor], seed: int = 0) -> dict[str, torch.Tensor]:
    """Deterministic weights with sane scales for every tensor of ``state`` (in its key order)."""
    g = torch.Generator().manual_seed(seed)
    out = {}
    for k, v in state.items():
        r = torch.randn(v.shape, generator=g, dtype=torch.float32)
        if k.endswith(("beta", "gamma")):
            r = 0.5 * r
        elif "norm" in k and k.endswith("weight"):
            r = 1 + 0.1 * r
        elif v.dim() >= 2:
            fan = v[0].numel() if "transposed" not in k else v.shape[0] * v[0, 0].numel()
            r = r / math.sqrt(fan)
        else:
            r = 0.05 * r
        out[k] = r
    return out


def golden_inputs() -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(123)
    return torch.rand(1, 26, 8, 8, generator=g), 2 * torch.randn(1, 4, 2, 8, 8, generator=g)


def make_pair(batch=1, size=(16, 16), channels=3, num=3000, seed=0, **kwargs) -> EventFrames:
    """Two 100 us exposures [0, 100) and [120, 220) with random events over [-50, 300)."""
    ev = random_events(num, size, (-50.0, 300.0), batch_size=batch, seed=seed)
    g = torch.Generator().manual_seed(seed)
    return EventFrames(torch.rand(batch, channels, *size, generator=g), ev, torch.zeros(batch),
                       torch.full((batch,), 100.0), blurry_next=torch.rand(batch, channels, *size, generator=g),
                       exposure_start_next=torch.full((batch,), 120.0), exposure_end_next=torch.full((batch,), 220.0),
                       **kwargs)


def one_event_per_pixel(t, p, size=(1, None)) -> Events:
    t = torch.as_tensor(t, dtype=torch.float64)
    n = len(t)
    return Events(torch.arange(n), torch.zeros(n, dtype=torch.long), t, torch.as_tensor(p), sensor_size=(1, n))


def reference_voxel(x, y, t, p, t0, t1, num_bins, height, width):
    """Independent per-event loop of the E2VID voxel grid over [t0, t1) with the official first/last mapping."""
    grid = np.zeros((num_bins, height, width))
    inside = [i for i in range(len(t)) if t0 <= t[i] < t1]
    if not inside:
        return grid
    first, last = t[inside[0]], t[inside[-1]]
    span = (last - first) or 1.0
    for i in inside:
        u = (num_bins - 1) * (t[i] - first) / span
        k = int(math.floor(u))
        grid[k, y[i], x[i]] += p[i] * (1 - (u - k))
        if k + 1 < num_bins:
            grid[k + 1, y[i], x[i]] += p[i] * (u - k)
    return grid


# ------------------------------------------------------------------------------------------ network
def test_matches_official_outputs():
    """Outputs of the official FinalBidirectionAttenfusion (run once with the same weights and inputs)."""
    net = REFIDNet().eval()
    net.load_state_dict(synthetic_state(net.state_dict(), seed=0), strict=True)
    x, e = golden_inputs()
    with torch.no_grad():
        y = net(x, e)
    assert y.shape == (1, 4, 3, 8, 8)
    torch.testing.assert_close(y.sum((0, 2, 3, 4)), torch.tensor(SUMS), atol=2e-3, rtol=1e-4)
    torch.testing.assert_close(y.abs().sum((0, 2, 3, 4)), torch.tensor(ABSSUMS), atol=2e-3, rtol=1e-4)
    torch.testing.assert_close(y[0, :, :, 3, 5].flatten(), torch.tensor(PIXELS), atol=1e-5, rtol=1e-4)


def tiny_net() -> REFIDNet:
    torch.manual_seed(0)
    net = REFIDNet(img_chn=4, base_num_channels=2, num_encoders=2).double()
    net.load_state_dict({k: v.double() for k, v in synthetic_state(net.state_dict(), seed=1).items()})
    return net


def test_unused_official_layers_get_no_gradient():
    net = tiny_net()
    net(torch.rand(1, 4, 4, 4, dtype=torch.float64), torch.randn(1, 2, 2, 4, 4, dtype=torch.float64)).sum().backward()
    for name in ("encoders_forward.1.conv.conv2d.weight", "encoders_backward.1.conv.conv2d.weight",
                 "encoders_forward.1.atten_fuse.se_2.1.weight", "encoders_backward.1.down.weight"):
        assert net.get_parameter(name).grad is None, name  # the last backward scale is never downsampled either
    assert net.get_parameter("encoders_backward.0.down.weight").grad.abs().sum() > 0


def test_gradcheck():
    net = tiny_net()
    x = torch.rand(1, 4, 4, 4, dtype=torch.float64, requires_grad=True)
    e = torch.randn(1, 2, 2, 4, 4, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda a, b: net(a, b), (x, e), eps=1e-6, atol=1e-5, fast_mode=True)


def test_network_shapes_and_non_contiguous():
    net = tiny_net()
    x = torch.rand(2, 4, 8, 12, dtype=torch.float64)
    e = torch.randn(2, 3, 2, 8, 12, dtype=torch.float64)
    y = net(x, e)
    assert y.shape == (2, 3, 3, 8, 12)
    x_nc = x.transpose(2, 3).contiguous().transpose(2, 3)
    e_nc = e.permute(0, 1, 2, 4, 3).contiguous().permute(0, 1, 2, 4, 3)
    assert not x_nc.is_contiguous() and not e_nc.is_contiguous()
    torch.testing.assert_close(net(x_nc, e_nc), y)
    torch.testing.assert_close(net(x.view(2, 2, 2, 8, 12), e), y)  # 5-D x is flattened


def test_network_exceptions():
    net = tiny_net()
    with pytest.raises(ValueError, match="multiples of 4"):
        net(torch.rand(1, 4, 6, 8, dtype=torch.float64), torch.randn(1, 2, 2, 6, 8, dtype=torch.float64))
    with pytest.raises(ValueError, match="4 channels"):
        net(torch.rand(1, 5, 8, 8), torch.randn(1, 2, 2, 8, 8))
    with pytest.raises(ValueError, match="event must be"):
        net(torch.rand(1, 4, 8, 8), torch.randn(1, 2, 8, 8))


# ---------------------------------------------------------------------------------------- voxel grid
def test_voxel_bilinear_split_and_polarity():
    ev = one_event_per_pixel([0.0, 31.25, 50.0], [1, -1, 1])  # window mode: u = 4 * t / 100 over 5 bins
    grid = refid_voxel_grid(ev, 0.0, 100.0, 5, normalize="window")[0, :, 0]
    expected = torch.zeros(5, 3)
    expected[0, 0] = 1.0  # u = 0
    expected[1, 1], expected[2, 1] = -0.75, -0.25  # u = 1.25, negative polarity
    expected[2, 2] = 1.0  # u = 2
    torch.testing.assert_close(grid, expected)


def test_voxel_official_mapping_by_first_and_last_event():
    ev = one_event_per_pixel([10.0, 25.0, 40.0, 70.0], [1, 1, -1, 1])
    grid = refid_voxel_grid(ev, 0.0, 100.0, 4)[0, :, 0]  # first 10 -> 0, last 70 -> 3: u = (t - 10) / 20
    expected = torch.zeros(4, 4)
    expected[0, 0] = 1.0
    expected[0, 1], expected[1, 1] = 0.25, 0.75  # u = 0.75
    expected[1, 2], expected[2, 2] = -0.5, -0.5  # u = 1.5
    expected[3, 3] = 1.0  # u = 3: the last bin, nothing beyond it
    torch.testing.assert_close(grid, expected)


def test_voxel_window_inclusion():
    ev = one_event_per_pixel([-1.0, 0.0, 50.0, 99.0, 100.0, 150.0], [1, 1, 1, 1, 1, 1])
    grid = refid_voxel_grid(ev, 0.0, 100.0, 3, normalize="window")[0, :, 0]
    assert grid.sum(0).tolist() == [0.0, 1.0, 1.0, 1.0, 0.0, 0.0]  # [start, end): t = end is out
    assert grid[1, 2] == 1.0  # t = 50 -> u = 1


def test_voxel_single_timestamp_goes_to_first_bin():
    ev = one_event_per_pixel([30.0, 30.0], [1, -1])
    grid = refid_voxel_grid(ev, 0.0, 100.0, 4)[0, :, 0]
    assert grid[0].tolist() == [1.0, -1.0] and grid[1:].abs().sum() == 0


def test_voxel_matches_reference_and_conserves_polarity():
    ev = random_events(400, (3, 5), (0.0, 1000.0), batch_size=2, seed=4)
    start, end = torch.tensor([100.0, 0.0]), torch.tensor([900.0, 600.0])
    grid = refid_voxel_grid(ev, start, end, 7)
    assert grid.shape == (2, 7, 3, 5) and grid.dtype == torch.float32
    for b in range(2):
        s = ev.sample(b)
        ref = reference_voxel(s.x.tolist(), s.y.tolist(), s.t.tolist(), s.p.tolist(), float(start[b]), float(end[b]),
                              7, 3, 5)
        np.testing.assert_allclose(grid[b].numpy(), ref, atol=1e-5)
        inside = s.select((s.t >= start[b]) & (s.t < end[b]))
        per_pixel = torch.zeros(15, dtype=torch.float64).index_add_(0, inside.pixel_index(), inside.p.double())
        torch.testing.assert_close(grid[b].sum(0).flatten().double(), per_pixel, atol=1e-5, rtol=0)


def test_voxel_exceptions():
    ev = one_event_per_pixel([1.0], [1])
    with pytest.raises(ValueError, match="num_bins"):
        refid_voxel_grid(ev, 0.0, 10.0, 0)
    with pytest.raises(ValueError, match="normalize"):
        refid_voxel_grid(ev, 0.0, 10.0, 3, normalize="minmax")


def test_latency_shift_moves_events_between_bins():
    # window mode, 11 bins over [0, 100): bin k at t = 10 k. Pixel 0 is stamped 20 us late.
    ev = one_event_per_pixel([50.0, 50.0], [1, 1])
    latency = torch.tensor([[[[20.0, 0.0]]]])
    before = refid_voxel_grid(ev, 0.0, 100.0, 11, normalize="window")[0, :, 0]
    after = refid_voxel_grid(ev.shift(latency), 0.0, 100.0, 11, normalize="window")[0, :, 0]
    assert before[5].tolist() == [1.0, 1.0]
    assert after[3, 0] == 1.0 and after[5, 0] == 0.0 and after[5, 1] == 1.0
    # official mapping: a constant shift inside the window changes nothing (bins follow the events) ...
    ev3 = one_event_per_pixel([20.0, 50.0, 80.0], [1, 1, 1])
    ref = refid_voxel_grid(ev3, 0.0, 100.0, 4)
    torch.testing.assert_close(refid_voxel_grid(ev3.shift(15.0), 0.0, 100.0, 4), ref)
    # ... but a per-pixel latency does: the middle event moves from u = 1.5 to u = 0.75
    moved = refid_voxel_grid(ev3.shift(torch.tensor([[[[0.0, 15.0, 0.0]]]])), 0.0, 100.0, 4)[0, :, 0]
    assert moved[:, 1].tolist() == [0.25, 0.75, 0.0, 0.0] and ref[0, :, 0, 1].tolist() == [0.0, 0.5, 0.5, 0.0]
    # and a constant shift moves events across the window border
    late = one_event_per_pixel([20.0, 50.0, 105.0], [1, 1, 1])
    assert refid_voxel_grid(late, 0.0, 100.0, 4).abs().sum() == 2.0
    assert refid_voxel_grid(late.shift(10.0), 0.0, 100.0, 4).abs().sum() == 3.0


# ----------------------------------------------------------------------------------- input layout
def test_window_and_output_times():
    frames = make_pair()  # exposures [0, 100) and [120, 220): m = 11, n = 1 -> delta = 220 / 23
    start, end, delta = refid_window(frames)
    d = 220.0 / 23
    torch.testing.assert_close(delta, torch.tensor([d], dtype=torch.float64))
    torch.testing.assert_close(start, torch.tensor([-d / 2], dtype=torch.float64))
    torch.testing.assert_close(end, torch.tensor([220.0 + d / 2], dtype=torch.float64))
    times = refid_output_times(frames)
    assert times.shape == (1, 23)
    assert float(times[0, 11]) == pytest.approx(110.0)  # the middle output is the gap's midpoint
    assert float(times[0, 0]) == pytest.approx(d / 2)
    start, end, delta = refid_window(frames, frame_offset=0.0)  # HighREV: exposure = first .. last sharp frame
    assert float(delta) == pytest.approx(220.0 / 22) and float(start) == pytest.approx(-10.0)
    deblur = refid_output_times(frames, mode="deblur")
    assert deblur.shape == (1, 11) and float(deblur[0, 5]) == pytest.approx(50.0)  # mid-exposure
    start, end, _ = refid_window(frames, mode="deblur")
    assert float(start) == pytest.approx(-100 / 22) and float(end) == pytest.approx(100 + 100 / 22)


def test_inputs_layout():
    frames = make_pair(batch=2)
    x, event = refid_inputs(frames)
    assert x.shape == (2, 26, 16, 16) and event.shape == (2, 23, 2, 16, 16)
    start, end, _ = refid_window(frames)
    voxel = refid_voxel_grid(frames.events, start, end, 24)
    torch.testing.assert_close(x[:, :3], frames.blurry)
    torch.testing.assert_close(x[:, 3:13], voxel[:, 1:11])
    torch.testing.assert_close(x[:, 13:16], frames.blurry_next)
    torch.testing.assert_close(x[:, 16:], voxel[:, 14:24])
    for i in (0, 11, 22):
        torch.testing.assert_close(event[:, i], voxel[:, i:i + 2])
    x, event = refid_inputs(frames, mode="deblur")
    assert x.shape == (2, 13, 16, 16) and event.shape == (2, 11, 2, 16, 16)
    start, end, _ = refid_window(frames, mode="deblur")
    torch.testing.assert_close(x[:, 3:], refid_voxel_grid(frames.events, start, end, 12)[:, 1:11])


def test_inputs_use_corrected_events_and_grey():
    frames = make_pair(channels=1)
    x, event = refid_inputs(frames, m=3, n=1)
    assert x.shape == (1, 10, 16, 16) and event.shape == (1, 7, 2, 16, 16)
    torch.testing.assert_close(x[:, :3], frames.blurry.expand(-1, 3, -1, -1))
    shifted = frames.events.shift(torch.rand(1, 1, 16, 16, dtype=torch.float64) * 40)
    _, event_corr = refid_inputs(frames.replace(corrected=shifted), m=3, n=1)
    _, event_ref = refid_inputs(frames.replace(events=shifted), m=3, n=1)
    torch.testing.assert_close(event_corr, event_ref)
    assert not torch.allclose(event_corr, event)


def test_nearest_frames():
    out = torch.arange(4.0).view(1, 4, 1, 1, 1).expand(2, 4, 1, 2, 2)
    times = torch.tensor([[0.0, 10.0, 20.0, 30.0], [5.0, 15.0, 25.0, 35.0]])
    got = nearest_frames(out, times, torch.tensor([[19.0, 1.0], [34.0, 16.0]]))
    assert got.shape == (2, 2, 1, 2, 2) and got[:, :, 0, 0, 0].tolist() == [[2.0, 0.0], [3.0, 1.0]]


# ------------------------------------------------------------------------------------------ adapter
def small_adapter(**kwargs) -> REFIDAdapter:
    torch.manual_seed(0)
    return REFIDAdapter(m=2, n=1, **kwargs)


def test_adapter_output_times():
    frames = make_pair()
    out = small_adapter()(frames)
    torch.testing.assert_close(out.meta["output_times"], refid_output_times(frames, 2, 1))


def test_adapter_official_size_on_8x8():
    adapter = REFIDAdapter(m=11)
    out = adapter(make_pair(size=(8, 8), num=500))
    assert out.output.shape == (1, 23, 3, 8, 8) and out.meta["output_times"].shape == (1, 23)
    deblur = REFIDAdapter(mode="deblur")
    assert deblur.net.img_chn == 13
    assert deblur(make_pair(size=(8, 8), num=500)).output.shape == (1, 11, 3, 8, 8)


def test_adapter_equals_function():
    adapter = small_adapter()
    frames = make_pair(batch=2)
    with torch.no_grad():
        expected = adapter.net(*refid_inputs(frames, 2, 1)).clamp(0, 1)
        got = adapter(frames).output
    torch.testing.assert_close(got, expected)
    nearest = small_adapter(select="nearest")(frames.replace(target_times=torch.tensor([[110.0], [0.0]])))
    assert nearest.output.shape == (2, 1, 3, 16, 16)
    torch.testing.assert_close(nearest.output[0, 0], expected[0, 2])  # middle of 5 outputs
    torch.testing.assert_close(nearest.output[1, 0], expected[1, 0])
    assert nearest.meta["output_times"].shape == (2, 1)


def test_adapter_exceptions():
    frames = make_pair()
    single = EventFrames(frames.blurry, frames.events, frames.exposure_start, frames.exposure_end)
    with pytest.raises(ValueError, match="blurry_next"):
        small_adapter()(single)
    assert small_adapter(mode="deblur")(single).output.shape == (1, 2, 3, 16, 16)
    with pytest.raises(ValueError, match="mode"):
        REFIDAdapter(mode="denoise")
    with pytest.raises(ValueError, match="m "):
        REFIDAdapter(m=1)
    with pytest.raises(ValueError, match="target_times"):
        small_adapter(select="nearest")(frames)
    overlap = frames.replace(exposure_start_next=torch.tensor([50.0]))
    with pytest.raises(ValueError, match="next exposure"):
        small_adapter()(overlap)


# ------------------------------------------------------------------------------------- checkpoints
@pytest.fixture(scope="module")
def official_state() -> dict[str, torch.Tensor]:
    return synthetic_state(REFIDNet().state_dict(), seed=5)


def test_released_checkpoint_layout_gives_m_11(tmp_path, official_state):
    path = tmp_path / "refid.pth"
    torch.save({"params": official_state}, path)
    adapter = REFIDAdapter(checkpoint=str(path))
    assert adapter.m == 11  # read from the 26 input channels of the released layout
    loaded = adapter.net.state_dict()
    assert all(torch.equal(loaded[k], v) for k, v in official_state.items())


def test_default_layout_matches_the_weights(tmp_path):
    assert REFIDAdapter().m == 4 and REFIDAdapter().net.img_chn == 12  # the shipped 4+1 layout
    assert REFIDAdapter(m=11).net.img_chn == 26
    path = tmp_path / "refid-6.pth"
    torch.save({"params": synthetic_state(REFIDNet(img_chn=16).state_dict(), seed=2)}, path)
    assert REFIDAdapter(checkpoint=str(path)).m == 6
    assert REFIDAdapter(mode="deblur").m == 11


def test_checkpoint_mismatch_raises(tmp_path, official_state):
    path = tmp_path / "refid.pth"
    torch.save({"params": official_state}, path)
    with pytest.raises(ValueError, match="head_img"):  # 26-channel interpolation weights, 13-channel deblur net
        REFIDAdapter(checkpoint=str(path), mode="deblur")

