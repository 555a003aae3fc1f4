from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F
from hypothesis import given, settings
from hypothesis import strategies as st

from evlatcorr import EventFrames, Events
from evlatcorr.adapters.gem import SAN, GEMAdapter, San, gem_eger
from tests.conftest import random_events


@pytest.fixture(scope="module", autouse=True)
def _one_thread():
    """The inputs here are tiny: one intra-op thread is as fast, and far faster when the CPU is shared
    (OpenMP threads of a busy machine wait for each other)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def net() -> San:
    torch.manual_seed(0)
    return San().eval()


def seeded_weights(state: dict, seed: int = 0, offset_gain: float = 1.0) -> dict:
    """Deterministic weights by state_dict order: U(-1, 1) / sqrt(fan_in); offset convs scaled by a gain."""
    g = torch.Generator().manual_seed(seed)
    out = {}
    for k, v in state.items():
        fan = v[0].numel() if v.dim() > 1 else 1
        out[k] = (torch.rand(v.shape, generator=g, dtype=torch.float64) * 2 - 1).float() / fan**0.5
        if "conv_offset_mask" in k:
            out[k] = out[k] * offset_gain
    return out


def ev(xs, ts, ps, width=8, height=1, ys=None, batch=None, batch_size=None) -> Events:
    n = len(ts)
    y = torch.zeros(n, dtype=torch.long) if ys is None else torch.tensor(ys)
    return Events(torch.tensor(xs), y, torch.tensor(ts, dtype=torch.float64), torch.tensor(ps),
                  None if batch is None else torch.tensor(batch), sensor_size=(height, width),
                  batch_size=batch_size)


def frames_from(events: Events, start, end, blurry: torch.Tensor | None = None, channels: int = 3,
                **kw) -> EventFrames:
    b = events.batch_size
    h, w = events.sensor_size
    if blurry is None:
        blurry = torch.rand(b, channels, h, w, generator=torch.Generator().manual_seed(5))
    return EventFrames(blurry, events, torch.as_tensor(start, dtype=torch.float64).expand(b),
                       torch.as_tensor(end, dtype=torch.float64).expand(b), **kw)


def channel(bin_: int, segment: int, positive: bool) -> int:
    return bin_ * 6 + segment * 2 + int(positive)


# the network ----------------------------------------------------------------------------------
def test_lightning_checkpoint_loads_the_student_not_the_teacher(tmp_path, net):
    # the official MInterface saves the student as model.* and a frozen copy as teacher_model.*
    g = torch.Generator().manual_seed(1)
    state = {k: torch.randn(v.shape, generator=g) for k, v in net.state_dict().items()}
    torch.save({"epoch": 3, "state_dict": {**{f"model.{k}": v for k, v in state.items()},
                                           **{f"teacher_model.{k}": -v for k, v in state.items()}}},
               tmp_path / "gem.ckpt")
    adapter = GEMAdapter(checkpoint=str(tmp_path / "gem.ckpt"))
    for k, v in adapter.net.state_dict().items():
        assert torch.equal(v, state[k]), k


# outputs of the official implementation (codes/model/san.py @33891b3 with the DCN extension replaced by
# torchvision.ops.deform_conv2d, CPU fp32, eval, no_grad) for seeded_weights(seed 0, offset_gain) and the
# inputs of _official_inputs (event map at half the image resolution): sums of L and E, two pixels
OFFICIAL = {
    1.0: {"L_sum": 5597.802435576261, "E_sum": 11223.96274214983,
          "L_1_5_7": [0.4695545, 0.917484, 0.2518444], "E_0_31_40": [1.1849005, 1.3147396, 1.0355446]},
    # offsets up to ~70 px: exercises the deformable sampling far outside the feature maps
    40.0: {"L_sum": 5494.784495791202, "E_sum": 11019.83723628521,
           "L_1_5_7": [0.4380817, 0.8946972, 0.2509149], "E_0_31_40": [1.1696379, 1.3083436, 1.0443183]},
}


def _official_inputs():
    g = torch.Generator().manual_seed(1)
    blur = torch.rand(2, 3, 32, 48, generator=g, dtype=torch.float64).float()
    event = torch.randint(0, 4, (2, 96, 16, 24), generator=g).float()
    return event, blur


@pytest.mark.parametrize("offset_gain", [1.0, 40.0])
def test_matches_official_outputs(net, offset_gain):
    ref = OFFICIAL[offset_gain]
    model = San().eval()
    model.load_state_dict(seeded_weights(model.state_dict(), 0, offset_gain))
    event, blur = _official_inputs()
    with torch.no_grad():
        latent, ratio = model(event, blur)
    assert latent.shape == ratio.shape == (2, 3, 32, 48)
    assert float(latent.double().sum()) == pytest.approx(ref["L_sum"], abs=1e-3)
    assert float(ratio.double().sum()) == pytest.approx(ref["E_sum"], abs=1e-3)
    torch.testing.assert_close(latent[1, :, 5, 7], torch.tensor(ref["L_1_5_7"]), rtol=0, atol=1e-6)
    torch.testing.assert_close(ratio[0, :, 31, 40], torch.tensor(ref["E_0_31_40"]), rtol=0, atol=1e-6)


def test_output_is_blur_times_ratio(net):
    g = torch.Generator().manual_seed(2)
    blur = torch.rand(1, 3, 32, 32, generator=g)
    event = torch.randint(0, 3, (1, 96, 32, 32), generator=g).float()
    with torch.no_grad():
        latent, ratio = net(event, blur)
    assert bool((ratio > 0).all())
    torch.testing.assert_close(latent, blur * ratio, rtol=1e-6, atol=1e-7)
    # a fresh network: zero offsets (mask 0.5) -> the fusion's deformable conv is 0.5 * conv + bias
    dcn = net.msff2.dcn
    x = torch.rand(1, 32, 6, 7, generator=g)
    with torch.no_grad():
        ref = 0.5 * F.conv2d(x, dcn.weight, None, padding=1) + dcn.bias[:, None, None]
        torch.testing.assert_close(dcn(x), ref, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize(("axis", "shift"), [(0, 1.0), (1, 1.0), (1, -2.0)])
def test_deformable_conv_offset_layout(axis, shift):
    # a constant integer offset for every tap (dy in even, dx in odd channels of the first two thirds)
    # and mask ~1 (logit 30) turn DCNv2 into a plain convolution of the shifted, zero-padded input
    model = San()
    dcn = model.msff2.dcn
    k2 = 9
    with torch.no_grad():
        dcn.conv_offset_mask.weight.zero_()
        bias = torch.zeros(3 * k2)
        bias[axis: 2 * k2: 2] = shift
        bias[2 * k2:] = 30.0
        dcn.conv_offset_mask.bias.copy_(bias)
        x = torch.rand(1, 32, 7, 9, generator=torch.Generator().manual_seed(3))
        # big[Y, X] = conv output centred at (Y - 2, X - 2), zero padding extended far enough
        big = F.conv2d(F.pad(x, (3, 3, 3, 3)), dcn.weight, dcn.bias)
        sy, sx = (int(shift), 0) if axis == 0 else (0, int(shift))
        ref = big[..., 2 + sy: 2 + sy + 7, 2 + sx: 2 + sx + 9]  # centred at (y + dy, x + dx)
        torch.testing.assert_close(dcn(x), ref, rtol=1e-5, atol=1e-5)


def _implicit_query_reference(query, ev_feat, im_feat):
    """The MSFF local implicit query from its definition, one pixel at a time, float64.

    Cell centres ``-1 + (2 i + 1) / n`` are computed in float32 as the official ``make_coord`` does
    (``(-1 + 1/n) + (2/n) * i``): where the two clamped look-ups at the border hit the same cell, the
    relative offset is that rounding error and, against the 1e-9 floor, sets the weights.
    """
    _, c, height, width = im_feat.shape
    he, we = ev_feat.shape[-2:]
    eps = 1e-6

    def centre(i: int, n: int) -> float:
        return float(((-1 + 1 / n) + (2 / n) * torch.arange(n).float())[i])

    out = torch.zeros(height * width, c, dtype=torch.float64)
    for i in range(height):
        for j in range(width):
            cy, cx = centre(i, height), centre(j, width)
            preds, areas = [], []
            for vy in (-1, 1):
                for vx in (-1, 1):
                    py = min(max(cy + vy / he + eps, -1 + eps), 1 - eps)
                    px = min(max(cx + vx / we + eps, -1 + eps), 1 - eps)
                    iy, ix = math.floor((py + 1) / 2 * he), math.floor((px + 1) / 2 * we)
                    ii, jj = math.floor((py + 1) / 2 * height), math.floor((px + 1) / 2 * width)
                    rel = [(cy - centre(iy, he)) * he, (cx - centre(ix, we)) * we]
                    cell = [2 / height * he, 2 / width * we]
                    inp = torch.cat([ev_feat[0, :, iy, ix], torch.tensor(rel + cell, dtype=torch.float64),
                                     im_feat[0, :, ii, jj]])
                    preds.append(query.imnet(inp))
                    areas.append(abs(rel[0] * rel[1]) + 1e-9)
            total = sum(areas)
            out[i * width + j] = sum(p * a / total for p, a in zip(preds, reversed(areas)))
    return out


@pytest.mark.parametrize(("ev_size", "im_size"), [((3, 5), (8, 8)), ((8, 8), (8, 8)), ((6, 4), (4, 12))])
def test_implicit_event_query_matches_definition(ev_size, im_size):
    torch.manual_seed(4)
    query = San().msff1.mlp.double()
    g = torch.Generator().manual_seed(5)
    ev_feat = torch.randn(1, 16, *ev_size, generator=g, dtype=torch.float64)
    im_feat = torch.randn(1, 16, *im_size, generator=g, dtype=torch.float64)
    with torch.no_grad():
        got = query(ev_feat, im_feat)[0]
        ref = _implicit_query_reference(query, ev_feat, im_feat)
    torch.testing.assert_close(got, ref, rtol=1e-5, atol=1e-5)


def test_net_shapes_and_errors(net):
    with torch.no_grad():
        latent, ratio = net(torch.zeros(2, 96, 16, 16), torch.rand(2, 3, 16, 32))  # smallest sizes
        assert latent.shape == ratio.shape == (2, 3, 16, 32)
        assert net(torch.zeros(1, 96, 17, 23), torch.rand(1, 3, 48, 16))[0].shape == (1, 3, 48, 16)
    with pytest.raises(ValueError, match=r"multiples of 16, got \(H, W\)=\(40, 32\)"):
        net(torch.zeros(1, 96, 16, 16), torch.rand(1, 3, 40, 32))
    with pytest.raises(ValueError, match=r"at least 16x16, got \(h, w\)=\(15, 16\)"):
        net(torch.zeros(1, 96, 15, 16), torch.rand(1, 3, 32, 32))
    with pytest.raises(ValueError, match="event must have shape"):
        net(torch.zeros(1, 48, 16, 16), torch.rand(1, 3, 32, 32))
    with pytest.raises(ValueError, match="event must have shape"):
        net(torch.zeros(2, 96, 16, 16), torch.rand(1, 3, 32, 32))
    with pytest.raises(ValueError, match="blur must have shape"):
        net(torch.zeros(1, 96, 16, 16), torch.rand(1, 1, 32, 32))
    with pytest.raises(ValueError, match="initializor='kaiming'"):
        San(initializor="normal")
    assert SAN is San  # the paper's name


def test_net_non_contiguous_inputs(net):
    g = torch.Generator().manual_seed(6)
    blur = torch.rand(1, 3, 32, 16, generator=g).transpose(2, 3)
    event = torch.rand(1, 96, 16, 16, generator=g).transpose(2, 3)
    assert not blur.is_contiguous() and not event.is_contiguous()
    with torch.no_grad():
        torch.testing.assert_close(net(event, blur)[0], net(event.contiguous(), blur.contiguous())[0])


def test_gradcheck_small_input():
    torch.manual_seed(7)
    model = San().double()
    model.load_state_dict({k: v.double() for k, v in seeded_weights(model.state_dict(), 1, 5.0).items()})
    g = torch.Generator().manual_seed(8)
    blur = torch.rand(1, 3, 16, 16, generator=g, dtype=torch.float64, requires_grad=True)
    event = torch.rand(1, 96, 16, 16, generator=g, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda b, e: model(e, b)[0], (blur, event), fast_mode=True)


# EGER -------------------------------------------------------------------------------------------
def test_eger_known_answer_bins_segments_polarities():
    # exposure [100, 260): 16 bins of 10 us, target (default) at mid-exposure 180 -> segment 0 before, 2 after
    events = ev([0, 1, 2, 3, 4, 5, 6, 7], [99.999, 100.0, 109.999, 179.999, 180.0, 215.0, 259.999, 260.0],
                [1, -1, 1, -1, 1, 1, -1, 1])
    eger = gem_eger(events, 100.0, 260.0)
    assert eger.shape == (1, 96, 1, 8) and eger.dtype == torch.float32
    expected = torch.zeros(96, 8)
    expected[channel(0, 0, False), 1] = 1  # at the exposure start: first bin, before the target, negative
    expected[channel(0, 0, True), 2] = 1
    expected[channel(7, 0, False), 3] = 1  # just before the target
    expected[channel(8, 2, True), 4] = 1  # at the target: after it (the middle segment (ts, ts) is empty)
    expected[channel(11, 2, True), 5] = 1
    expected[channel(15, 2, False), 6] = 1  # just inside the end: last bin
    # x=0 (before the exposure) and x=7 (at its end: half-open) stay empty
    torch.testing.assert_close(eger[0, :, 0], expected, rtol=0, atol=0)
    # the middle segment collects [target_start, target_end); counts accumulate
    wide = gem_eger(ev([2, 2, 2, 2], [139.0, 140.0, 141.0, 200.0], [1, 1, 1, 1]), 100.0, 260.0, 140.0, 200.0)
    assert wide[0, channel(3, 0, True), 0, 2] == 1 and wide[0, channel(4, 1, True), 0, 2] == 2
    assert wide[0, channel(10, 2, True), 0, 2] == 1 and wide.sum() == 4


def test_eger_last_bin_clip():
    # (t - start) / interval rounds to num_bins for the last representable t < end: the official code
    # moves index num_bins to the last bin
    t = math.nextafter(0.5, -math.inf)
    assert (t + 1e6) / ((0.5 + 1e6) / 16) == 16.0
    eger = gem_eger(ev([1], [t], [1], width=2), -1e6, 0.5, 0.0, 0.0)
    assert eger[0, channel(15, 2, True), 0, 1] == 1 and eger.sum() == 1
    t3 = math.nextafter(1.0, -math.inf)
    assert math.floor(t3 / (1.0 / 3)) == 3
    eger3 = gem_eger(ev([0], [t3], [-1], width=2), 0.0, 1.0, num_bins=3)
    assert eger3.shape == (1, 18, 1, 2)
    assert eger3[0, channel(2, 2, False), 0, 0] == 1 and eger3.sum() == 1


def test_eger_scale_factor_batch_and_target_outside():
    # scale_factor 4 on a 9 x 10 sensor: a 2 x 2 map; rows 8 and columns 8, 9 fall outside and are dropped
    events = ev([0, 3, 7, 4, 9, 1, 2], [10.0, 20.0, 30.0, 40.0, 50.0, 60.0, 10.0], [1, 1, 1, -1, 1, 1, 1],
                width=10, height=9, ys=[0, 3, 5, 1, 0, 8, 0], batch=[0, 0, 0, 0, 0, 0, 1])
    start, end = torch.tensor([0.0, 0.0]), torch.tensor([160.0, 16.0])
    eger = gem_eger(events, start, end, scale_factor=4)
    assert eger.shape == (2, 96, 2, 2)
    assert eger[0, channel(1, 0, True), 0, 0] == 1 and eger[0, channel(2, 0, True), 0, 0] == 1
    assert eger[0, channel(3, 0, True), 1, 1] == 1 and eger[0, channel(4, 0, False), 0, 1] == 1
    assert eger[0].sum() == 4
    # sample 1: exposure [0, 16) -> 1 us bins, target at 8: t=10 is bin 10, after the target
    assert eger[1, channel(10, 2, True), 0, 0] == 1 and eger[1].sum() == 1
    # a target window before the exposure: every event is "after" it
    late = gem_eger(events, start, end, torch.tensor([-50.0, -50.0]), torch.tensor([-20.0, -20.0]))
    assert late.view(2, 16, 6, 9, 10)[:, :, 4:].sum() == late.sum() == 7  # segment 2 only: channels 6k + 4, 5


def _eger_reference(events: Events, start, end, ts, num_bins=16, scale=1):
    """Straight from the definition, one event at a time."""
    h, w = events.sensor_size[0] // scale, events.sensor_size[1] // scale
    out = torch.zeros(events.batch_size, 6 * num_bins, h, w)
    for x, y, t, p, b in zip(events.x.tolist(), events.y.tolist(), events.t.tolist(), events.p.tolist(),
                             events.batch.tolist()):
        s, e = float(start[b]), float(end[b])
        if not s <= t < e or y // scale >= h or x // scale >= w:
            continue
        index = min(math.floor((t - s) / ((e - s) / num_bins)), num_bins - 1)
        segment = 0 if t < float(ts[b]) else 2
        out[b, channel(index, segment, p > 0), y // scale, x // scale] += 1
    return out


@pytest.mark.parametrize("scale", [1, 2])
def test_eger_matches_reference_on_random_events(scale):
    events = random_events(3000, (9, 11), (0.0, 1e4), batch_size=2, seed=scale)
    start, end = torch.tensor([1000.0, 2500.0]), torch.tensor([9000.0, 6000.0])
    ts = start + 0.5 * (end - start)
    got = gem_eger(events, start, end, scale_factor=scale)
    torch.testing.assert_close(got, _eger_reference(events, start, end, ts, scale=scale), rtol=0, atol=0)
    # invariant: every event of the exposure (inside the map) is counted once
    inside = events.window(start, end)
    inside = inside.select((inside.y // scale < 9 // scale) & (inside.x // scale < 11 // scale))
    assert got.sum(dim=(1, 2, 3)).tolist() == inside.counts().float().tolist()


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 10_000), scale=st.integers(1, 3), start=st.floats(-500.0, 500.0),
       length=st.floats(1.0, 2000.0), target=st.floats(-0.2, 1.2), width=st.floats(0.0, 0.5))
def test_eger_conserves_counts_per_segment(seed, scale, start, length, target, width):
    # every event of the exposure inside the map is counted once, in the segment its time says
    events = random_events(300, (7, 8), (-600.0, 2600.0), batch_size=2, seed=seed)
    t_lo = start + target * length
    t_hi = t_lo + width * length
    eger = gem_eger(events, start, start + length, t_lo, t_hi, scale_factor=scale)
    inside = events.window(start, start + length)
    inside = inside.select((inside.y // scale < 7 // scale) & (inside.x // scale < 8 // scale))
    segments = eger.view(2, 16, 3, 2, *eger.shape[-2:]).sum(dim=(1, 3, 4, 5))  # (B, 3)
    for b in range(2):
        t = inside.t[inside.batch == b]
        expected = [int((t < t_lo).sum()), int(((t >= t_lo) & (t < t_hi)).sum()), int((t >= t_hi).sum())]
        assert segments[b].tolist() == expected
    polarity = eger.view(2, 16, 3, 2, *eger.shape[-2:]).sum(dim=(1, 2, 4, 5))  # (B, 2): negative, positive
    assert polarity[:, 1].tolist() == [int(((inside.batch == b) & (inside.p > 0)).sum()) for b in range(2)]


# checksums of the official gen_EGER (codes/data/utils.py @33891b3) on _official_events, exposure
# [1000, 8999), target span (4500, 4500); the scale-4 run gets the coordinates x // 4, y // 4 on a 10 x 12
# map
OFFICIAL_EGER = {
    1: {"sum": 2403, "channel_weighted": 114268, "pixel_weighted": 579036, "at_2_3": 4, "max": 4},
    4: {"sum": 2403, "channel_weighted": 114268, "pixel_weighted": 142340, "at_2_3": 18, "max": 5},
}


def _official_events(height, width):
    g = torch.Generator().manual_seed(7)
    x = torch.randint(0, width, (3000,), generator=g)
    y = torch.randint(0, height, (3000,), generator=g)
    t = torch.randint(0, 10000, (3000,), generator=g).sort().values
    p = torch.randint(0, 2, (3000,), generator=g) * 2 - 1
    return Events(x, y, t.double(), p, sensor_size=(height, width))


@pytest.mark.parametrize(("scale", "size"), [(1, (20, 24)), (4, (40, 48))])
def test_eger_matches_official_checksums(scale, size):
    ref = OFFICIAL_EGER[scale]
    eger = gem_eger(_official_events(*size), 1000.0, 8999.0, 4500.0, 4500.0, scale_factor=scale)[0].double()
    h, w = eger.shape[-2:]
    pix = (torch.arange(h)[:, None] * w + torch.arange(w)).double()
    assert eger.sum() == ref["sum"] and eger.max() == ref["max"]
    assert (eger * torch.arange(96).double()[:, None, None]).sum() == ref["channel_weighted"]
    assert (eger * pix).sum() == ref["pixel_weighted"] and eger[:, 2, 3].sum() == ref["at_2_3"]


def test_eger_argument_errors():
    events = random_events(200, (4, 4), (0.0, 100.0), batch_size=2, seed=3)
    start, end = torch.tensor([0.0, 0.0]), torch.tensor([100.0, 90.0])
    with pytest.raises(ValueError, match="num_bins must be a positive integer"):
        gem_eger(events, start, end, num_bins=0)
    with pytest.raises(ValueError, match="scale_factor must be a positive integer"):
        gem_eger(events, start, end, scale_factor=1.5)
    with pytest.raises(ValueError, match="larger than the sensor"):
        gem_eger(events, start, end, scale_factor=5)
    with pytest.raises(ValueError, match="target_end must not be before"):
        gem_eger(events, start, end, 50.0, 40.0)
    with pytest.raises(ValueError, match="target_end needs target_start"):
        gem_eger(events, start, end, None, 40.0)


def test_latency_shift_moves_events_between_bins():
    # exposure [0, 160): 10 us bins, target 80. x=2: t=75 (bin 7, before); x=3: t=85 (bin 8, after)
    events = ev([2, 3, 0], [75.0, 85.0, 120.0], [1, -1, 1], width=4)
    latency = torch.tensor([0.0, 0.0, 30.0, 10.0]).view(1, 1, 1, 4)
    frames = frames_from(events, 0.0, 160.0, blurry=torch.rand(1, 3, 1, 4))
    adapter = GEMAdapter()
    before = adapter.representation(frames)[0, :, 0]
    after = adapter.representation(frames.replace(corrected=events.shift(latency), latency=latency))[0, :, 0]
    assert before[channel(7, 0, True), 2] == 1 and before[channel(8, 2, False), 3] == 1
    assert after[channel(4, 0, True), 2] == 1  # 75 - 30 = 45: three bins earlier
    assert after[channel(7, 0, False), 3] == 1  # 85 - 10 = 75: across the target, into the segment before it
    assert torch.equal(before[:, 0], after[:, 0])  # no latency at x=0
    assert before.sum() == after.sum() == 3
    # a constant latency moves events into and out of the exposure
    edge = ev([0, 1], [-5.0, 165.0], [1, 1], width=2)
    shifted = gem_eger(edge.shift(10.0), 0.0, 160.0)[0, :, 0]
    assert shifted[:, 0].sum() == 0 and shifted[channel(15, 2, True), 1] == 1


# adapter -----------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def adapter() -> GEMAdapter:
    torch.manual_seed(0)
    return GEMAdapter().eval()


@pytest.mark.parametrize("scale_factor", [1, 2])
def test_adapter_is_the_network_on_the_eger_and_the_bgr_frame(adapter, scale_factor):
    frames = frames_from(random_events(2000, (32, 32), (0.0, 1e4), seed=1), 1000.0, 9000.0)
    model = GEMAdapter(scale_factor=scale_factor)
    model.net.load_state_dict(adapter.net.state_dict())
    size = 32 // scale_factor
    with torch.no_grad():
        eger = gem_eger(frames.events, frames.exposure_start, frames.exposure_end, scale_factor=scale_factor)
        assert model.representation(frames).shape == eger.shape == (1, 96, size, size)
        latent = model.net(eger, frames.blurry.flip(1))[0]  # BGR for the network
        out = model(frames).output
    torch.testing.assert_close(out, latent.clamp(0, 1).flip(1))


def test_adapter_output_is_blurry_times_ratio_clamped(adapter):
    events = random_events(2000, (16, 16), (0.0, 1e4), seed=3)
    frames = frames_from(events, 1000.0, 9000.0)
    raw, clamped = GEMAdapter(clamp=False), GEMAdapter()
    with torch.no_grad():
        for model in (raw, clamped):
            model.net.load_state_dict(adapter.net.state_dict())
            model.net.dec.conv.bias.add_(2.0)  # E around 2: brightening, so that the clamp matters
        raw_out, out = raw(frames).output, clamped(frames).output
        ratio = raw.net(raw.representation(frames), frames.blurry.flip(1))[1].flip(1)
    torch.testing.assert_close(raw_out, frames.blurry * ratio, rtol=1e-6, atol=1e-7)
    assert float(raw_out.max()) > 1.0 and float(out.max()) == 1.0 and float(out.min()) >= 0.0
    assert torch.equal(raw_out.clamp(0, 1), out)


def test_adapter_rgb_order_grey_and_non_contiguous(adapter):
    events = random_events(800, (16, 32), (0.0, 1e4), seed=4)
    frames = frames_from(events, 0.0, 1e4)
    rgb = GEMAdapter(bgr=False)
    rgb.net.load_state_dict(adapter.net.state_dict())
    with torch.no_grad():
        a = adapter(frames).output
        b = rgb(frames.replace(blurry=frames.blurry.flip(1).contiguous())).output
        torch.testing.assert_close(a, b.flip(1))
        grey = torch.rand(1, 32, 16, generator=torch.Generator().manual_seed(0)).transpose(1, 2)[:, None]
        assert not grey.is_contiguous()
        out = adapter(frames.replace(blurry=grey)).output
        eger = adapter.representation(frames)
        ref = adapter.net(eger, grey.expand(-1, 3, -1, -1))[0].clamp(0, 1).mean(1, keepdim=True)
    assert out.shape == (1, 1, 16, 32)
    torch.testing.assert_close(out, ref)


def test_adapter_target_times(adapter):
    events = random_events(1500, (16, 16), (0.0, 1e4), seed=2)
    frames = frames_from(events, 2000.0, 8000.0)
    with torch.no_grad():
        a = adapter(frames).output
        mid = adapter(frames.replace(target_times=torch.tensor([[5000.0]]))).output
        early = adapter(frames.replace(target_times=torch.tensor([[3000.0]]))).output
    torch.testing.assert_close(mid, a)  # mid-exposure is the default target
    assert not torch.equal(early, a)
    assert adapter.target_time(frames).tolist() == [5000.0]
    quarter = GEMAdapter(predict_ts=0.25)
    assert quarter.target_time(frames).tolist() == [3500.0]


def test_adapter_event_map_size_and_arguments():
    small = frames_from(random_events(300, (32, 32), (0.0, 1e4), seed=6), 0.0, 1e4)
    with pytest.raises(ValueError, match=r"event map to be at least 16x16.*scale_factor 4 = \(8, 8\)"):
        GEMAdapter(scale_factor=4, pad=False)(small)
    with torch.no_grad():  # padded to 64x64, a 16x16 event map
        assert GEMAdapter(scale_factor=4)(small).output.shape == (1, 3, 32, 32)
    with pytest.raises(ValueError, match="scale_factor must be a positive integer"):
        GEMAdapter(scale_factor=0)
    with pytest.raises(ValueError, match="predict_ts must be"):
        GEMAdapter(predict_ts=1.5)

