from __future__ import annotations

import kornia
import pytest
import torch

from evlatcorr import EventFrames, Events
from evlatcorr.adapters import EFNetAdapter
from evlatcorr.adapters.efnet import EFNet, efnet_event_mask, efnet_scer
from tests.conftest import random_events


@pytest.fixture(scope="module")
def net() -> EFNet:
    return EFNet().eval()


def seeded_weights(state: dict, seed: int = 0) -> dict:
    """Deterministic weights by state_dict order: U(-1, 1) / sqrt(fan_in)."""
    g = torch.Generator().manual_seed(seed)
    out = {}
    for k, v in state.items():
        fan = v[0].numel() if v.dim() > 1 else 1
        out[k] = (torch.rand(v.shape, generator=g, dtype=torch.float64) * 2 - 1).float() / fan**0.5
    return out


def frames_from(events: Events, start, end, blurry: torch.Tensor | None = None, **kw) -> EventFrames:
    b = events.batch_size
    h, w = events.sensor_size
    if blurry is None:
        blurry = torch.rand(b, 3, h, w, generator=torch.Generator().manual_seed(5))
    return EventFrames(blurry, events, torch.as_tensor(start, dtype=torch.float64).expand(b),
                       torch.as_tensor(end, dtype=torch.float64).expand(b), **kw)


def ev(xs, ts, ps, width=8, batch=None, batch_size=None) -> Events:
    """Events on a 1-row sensor (y = 0)."""
    n = len(ts)
    return Events(torch.tensor(xs), torch.zeros(n, dtype=torch.long), torch.tensor(ts, dtype=torch.float64),
                  torch.tensor(ps), None if batch is None else torch.tensor(batch), sensor_size=(1, width),
                  batch_size=batch_size)


# the network ----------------------------------------------------------------------------------
# outputs of the official implementation (EFNet_arch.py @7cf6737, wf=8, CPU fp32) for
# seeded_weights(seed 0) and the inputs of _official_inputs: sums and two pixels of out_2
OFFICIAL = {
    "out_1_sum": 186.35622,
    "none": {"out_2_sum": 339.57272, "px_3_5": [1.5958110, 1.1383466, 0.3039186],
             "px_7_11": [1.2928826, 0.8600640, 1.5655012]},
    "mask": {"out_2_sum": 374.10018, "px_3_5": [1.7849221, 1.0581908, 0.6097487],
             "px_7_11": [1.3743324, 0.7380573, 1.6253977]},
}


def _official_inputs():
    g = torch.Generator().manual_seed(1)
    x = torch.rand(1, 3, 8, 12, generator=g, dtype=torch.float64).float()
    e = (torch.rand(1, 6, 8, 12, generator=g, dtype=torch.float64) * 2 - 1).float()
    m = (torch.rand(1, 1, 8, 12, generator=g, dtype=torch.float64) > 0.5).float()
    return x, e, m


@pytest.mark.parametrize("use_mask", [False, True])
def test_matches_official_outputs(use_mask):
    small = EFNet(wf=8).eval()
    small.load_state_dict(seeded_weights(small.state_dict()))
    x, e, m = _official_inputs()
    with torch.no_grad():
        out_1, out_2 = small(x, e, m if use_mask else None)
    ref = OFFICIAL["mask" if use_mask else "none"]
    assert float(out_1.double().sum()) == pytest.approx(OFFICIAL["out_1_sum"], abs=1e-3)
    assert float(out_2.double().sum()) == pytest.approx(ref["out_2_sum"], abs=1e-3)
    torch.testing.assert_close(out_2[0, :, 3, 5], torch.tensor(ref["px_3_5"]), rtol=0, atol=1e-5)
    torch.testing.assert_close(out_2[0, :, 7, 11], torch.tensor(ref["px_7_11"]), rtol=0, atol=1e-5)


def test_net_shapes_and_errors(net):
    x, e = torch.rand(2, 3, 16, 20), torch.rand(2, 6, 16, 20) * 2 - 1
    with torch.no_grad():
        out = net(x, e, torch.ones(2, 1, 16, 20))
    assert isinstance(out, list) and [tuple(o.shape) for o in out] == [(2, 3, 16, 20)] * 2
    with pytest.raises(ValueError, match="multiples of 4"):
        net(torch.rand(1, 3, 16, 18), torch.rand(1, 6, 16, 18))
    with pytest.raises(ValueError, match="event must have shape"):
        net(x, torch.rand(2, 5, 16, 20))
    with pytest.raises(ValueError, match="mask must have shape"):
        net(x, e, torch.ones(2, 2, 16, 20))
    with pytest.raises(ValueError, match="fuse_before_downsample=True"):
        EFNet(fuse_before_downsample=False)


def test_gradcheck_tiny_net():
    torch.manual_seed(0)
    tiny = EFNet(wf=4).double()
    x = torch.rand(1, 3, 4, 4, dtype=torch.float64, requires_grad=True)
    e = torch.rand(1, 6, 4, 4, dtype=torch.float64) * 2 - 1
    m = torch.ones(1, 1, 4, 4, dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda a: tiny(a, e, m)[1], (x,), fast_mode=True)


# SCER -------------------------------------------------------------------------------------------
def test_scer_known_answer_span_events():
    # anchors at t=0 (x=0) and t=120 (x=7, the last event: in no channel) give t0=0, dt=120, t_mid=60,
    # edges 0, 20, 40, 60, 80, 100, 120
    events = ev([0, 1, 2, 3, 4, 5, 7], [0.0, 10.0, 45.0, 60.0, 99.9, 100.0, 120.0], [1, 1, 0, 1, 1, 0, 1])
    v = efnet_scer(events, -50.0, 500.0, normalize=False)[0, :, 0]  # (6, W)
    expected = torch.tensor([
        [-1, -1, 1, 0, 0, 0, 0, 0],  # ch0: -(sum in [0, 60))
        [0, 0, 1, 0, 0, 0, 0, 0],  # ch1: -(sum in [20, 60))
        [0, 0, 1, 0, 0, 0, 0, 0],  # ch2: -(sum in [40, 60))
        [0, 0, 0, 1, 0, 0, 0, 0],  # ch3: +(sum in [60, 80))
        [0, 0, 0, 1, 1, 0, 0, 0],  # ch4: +(sum in [60, 100))
        [0, 0, 0, 1, 1, -1, 0, 0],  # ch5: +(sum in [60, 120))
    ], dtype=torch.float32)
    torch.testing.assert_close(v, expected, rtol=0, atol=0)
    assert not torch.signbit(v).logical_and(v == 0).any()  # no negative zeros


def test_scer_exposure_window_edges():
    # span="exposure": t0, t1 = the exposure [0, 120); edges every 20 us
    events = ev([0, 1, 2, 3, 4], [-1e-3, 0.0, 59.999, 119.999, 120.0], [1, 1, 1, 1, 1], width=5)
    v = efnet_scer(events, 0.0, 120.0, normalize=False, span="exposure")[0, :, 0]
    assert v[:, 0].abs().sum() == 0  # just before the exposure: out
    assert v[:, 1].tolist() == [-1, 0, 0, 0, 0, 0]  # at the start: first bin
    assert v[:, 2].tolist() == [-1, -1, -1, 0, 0, 0]  # just before the middle: all left channels
    assert v[:, 3].tolist() == [0, 0, 0, 0, 0, 1]  # just inside the end: last channel only
    assert v[:, 4].abs().sum() == 0  # at the end: out (half-open exposure)


def test_scer_normalisation_batch_and_empty_sample():
    events = ev([0, 1, 1, 2, 3], [0.0, 10.0, 12.0, 70.0, 120.0], [1, 1, 1, 0, 1], width=4,
                batch=[0, 0, 0, 0, 0], batch_size=3)
    start, end = torch.tensor([0.0, 0.0, 0.0]), torch.tensor([200.0, 10.0, 10.0])
    raw = efnet_scer(events, start, end, normalize=False)
    assert raw.shape == (3, 6, 1, 4)
    assert float(raw[0].abs().max()) == 2.0  # two positive events at x=1 in the first bin
    norm = efnet_scer(events, start, end)
    torch.testing.assert_close(norm[0], raw[0] / 2)
    assert float(norm[0].abs().max()) == 1.0
    assert not norm[1:].any() and torch.isfinite(norm).all()  # samples without events stay zero


def _scer_reference(events: Events, start, end, num_bins: int = 6) -> torch.Tensor:
    """Straight from the definition: one mask per channel, one sample at a time."""
    h, w = events.sensor_size
    out = torch.zeros(events.batch_size, num_bins, h, w)
    for b in range(events.batch_size):
        s = events.sample(b).window(float(start[b]), float(end[b]))
        if len(s) == 0:
            continue
        t0, t1 = float(s.t[0]), float(s.t[-1])
        dt, mid = t1 - t0, t0 + (t1 - t0) / 2
        for c in range(num_bins):
            if c < num_bins // 2:
                sel, sign = (s.t >= t0 + dt / num_bins * c) & (s.t < mid), -1.0
            else:
                hi = t1 if c == num_bins - 1 else t0 + dt / num_bins * (c + 1)
                sel, sign = (s.t >= mid) & (s.t < hi), 1.0
            out[b, c].index_put_((s.y[sel], s.x[sel]), sign * s.p[sel].float(), accumulate=True)
    return out


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_scer_matches_reference_on_random_events(seed):
    events = random_events(3000, (9, 11), (0.0, 1e4), batch_size=2, seed=seed)
    start, end = torch.tensor([1000.0, 2500.0]), torch.tensor([9000.0, 6000.0])
    got = efnet_scer(events, start, end, normalize=False)
    torch.testing.assert_close(got, _scer_reference(events, start, end), rtol=0, atol=0)
    # invariant: -ch0 + ch5 = net polarity of all events in [t0, t1) (the last event excluded)
    total = torch.zeros(2, 9, 11)
    for b in range(2):
        s = events.sample(b).window(float(start[b]), float(end[b]))
        s = s.select(s.t < s.t[-1])
        total[b].index_put_((s.y, s.x), s.p.float(), accumulate=True)
    torch.testing.assert_close(got[:, 5] - got[:, 0], total, rtol=0, atol=0)


def test_scer_argument_errors():
    events = random_events(200, (4, 4), (0.0, 100.0), batch_size=2, seed=3)
    with pytest.raises(ValueError, match="num_bins must be a positive even"):
        efnet_scer(events, 0.0, 100.0, num_bins=5)
    with pytest.raises(ValueError, match="span must be"):
        efnet_scer(events, 0.0, 100.0, span="frame")


def test_latency_shift_moves_events_between_channels():
    # anchors (latency 0) at x=0, t=0 and x=1, t=120: t0=0, t_mid=60, edges every 20 us.
    # the event at x=2, t=70 (+1) is in ch3..5; with 30 us latency at x=2 it is at t=40: ch0..2, negated
    events = ev([0, 2, 1], [0.0, 70.0, 120.0], [1, 1, 1], width=4)
    latency = torch.tensor([0.0, 0.0, 30.0, 0.0]).view(1, 1, 1, 4)
    frames = frames_from(events, 0.0, 200.0, blurry=torch.rand(1, 3, 1, 4))
    adapter = EFNetAdapter(use_mask=False)
    before = adapter.representation(frames)[0][0, :, 0, 2]
    corrected = frames.replace(corrected=events.shift(latency), latency=latency)
    after = adapter.representation(corrected)[0][0, :, 0, 2]
    assert before.tolist() == [0, 0, 0, 1, 1, 1]
    assert after.tolist() == [-1, -1, -1, 0, 0, 0]
    # a constant latency shifts events into and out of the exposure (span="exposure")
    late = ev([0, 1], [-10.0, 130.0], [1, 1], width=2)
    v = efnet_scer(late.shift(20.0), 0.0, 120.0, normalize=False, span="exposure")[0, :, 0]
    assert v[:, 0].abs().sum() == 0 and v[:, 1].tolist() == [0, 0, 0, 0, 0, 1]


# mask ----------------------------------------------------------------------------------------------
def test_event_mask_known_answer():
    v = torch.zeros(1, 6, 7, 9)
    v[0, 0, 3, 2] = 0.5  # a horizontal pair with a one-pixel gap ...
    v[0, 5, 3, 4] = -0.5
    v[0, 2, 0, 8] = 1.0  # ... an isolated corner pixel
    v[0, 1, 6, 0] = 1.0
    v[0, 4, 6, 0] = -1.0  # several channels at one pixel
    m = efnet_event_mask(v)
    assert m.shape == (1, 1, 7, 9) and m.dtype == torch.float32
    expected = torch.zeros(7, 9)
    expected[3, 2:5] = 1  # the gap is closed
    expected[0, 8] = 1  # isolated pixels are kept: the border does not erode
    expected[6, 0] = 1
    torch.testing.assert_close(m[0, 0], expected, rtol=0, atol=0)
    assert efnet_event_mask(v.double()).dtype == torch.float64


def test_event_mask_equals_kornia_closing():
    g = torch.Generator().manual_seed(0)
    v = torch.where(torch.rand(2, 6, 15, 17, generator=g) > 0.93, torch.randn(2, 6, 15, 17, generator=g), 0.0)
    hit = (v != 0).any(1, keepdim=True).float()
    ref = kornia.morphology.closing(hit, torch.ones(3, 3), border_type="geodesic")
    torch.testing.assert_close(efnet_event_mask(v), ref, rtol=0, atol=0)
    with pytest.raises(ValueError, match="voxel must have shape"):
        efnet_event_mask(torch.zeros(6, 4, 4))


# adapter -----------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def adapter() -> EFNetAdapter:
    torch.manual_seed(0)
    return EFNetAdapter().eval()


def test_adapter_runs_the_network_on_the_scer_and_its_mask(adapter):
    events = random_events(2000, (32, 32), (0.0, 1e4), seed=1)
    frames = frames_from(events, 1000.0, 9000.0)
    with torch.no_grad():
        out = adapter(frames)
        voxel = efnet_scer(events, frames.exposure_start, frames.exposure_end)
        ref = adapter.net(frames.blurry, voxel, efnet_event_mask(voxel))[1].clamp(0, 1)
    torch.testing.assert_close(out.output, ref)
    with torch.no_grad():
        no_mask = EFNetAdapter(use_mask=False)
        no_mask.net.load_state_dict(adapter.net.state_dict())
        assert not torch.equal(no_mask(frames).output, out.output)  # the mask matters


def test_adapter_grey_is_the_mean_of_the_rgb_output_then_clamped(adapter):
    events = random_events(800, (16, 20), (0.0, 1e4), seed=4)
    grey = torch.rand(1, 20, 16, generator=torch.Generator().manual_seed(0)).transpose(1, 2)[:, None]
    assert not grey.is_contiguous()
    frames = frames_from(events, 0.0, 1e4, blurry=grey)
    raw = EFNetAdapter(clamp=False)
    raw.net.load_state_dict(adapter.net.state_dict())
    with torch.no_grad():
        out = adapter(frames).output
        rgb = raw(frames.replace(blurry=grey.expand(-1, 3, -1, -1).contiguous())).output
    assert out.shape == (1, 1, 16, 20)
    torch.testing.assert_close(out, rgb.mean(1, keepdim=True).clamp(0, 1))

