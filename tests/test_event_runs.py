from __future__ import annotations

import pytest
import torch

import evlatcorr.compiled
import evlatcorr.continuous
from evlatcorr.continuous import ContinuousIntegral
from evlatcorr.events import Events

FIELDS = ("pixel", "t", "step", "order", "run_start", "_after", "peak_count", "ignored")


def _events(seed: int = 0) -> Events:
    """Random events over 6x9 pixels (one pixel with none, runs of equal times), a hot pixel (90 ON events), and a
    pixel whose span is exactly the hot limit (75 ON events: θ = 0.2 → 15.000000223 in float32, over 15)."""
    g = torch.Generator().manual_seed(seed)
    n = 5000
    x, y = torch.randint(0, 9, (n,), generator=g), torch.randint(0, 6, (n,), generator=g)
    keep = ~((x == 8) & (y == 5))  # pixel (5, 8): no events
    x, y = x[keep], y[keep]
    t = torch.sort(torch.randint(0, 400, (len(x),), generator=g).double() * 2.5)[0]  # many equal times
    p = torch.randint(0, 2, (len(x),), generator=g) * 2 - 1
    hot_t = torch.linspace(10.0, 900.0, 90, dtype=torch.float64)
    edge_t = torch.linspace(20.0, 800.0, 75, dtype=torch.float64)
    x = torch.cat([x, torch.zeros(90, dtype=x.dtype), torch.full((75,), 4, dtype=x.dtype)])
    y = torch.cat([y, torch.zeros(90, dtype=y.dtype), torch.full((75,), 2, dtype=y.dtype)])
    t = torch.cat([t, hot_t, edge_t])
    p = torch.cat([p, torch.ones(165, dtype=p.dtype)])
    return Events(x, y, t, p, sensor_size=(6, 9), sort=True)


def _prepared(events: Events, compiled: bool, monkeypatch: pytest.MonkeyPatch, max_log_range: float | None = 15.0):
    monkeypatch.setattr(evlatcorr.compiled, "ENABLED", compiled)
    return ContinuousIntegral(events, 0.2, max_log_range=max_log_range)


@pytest.mark.parametrize("max_log_range", [15.0, None])
def test_compiled_preparation_equals_the_eager_one(monkeypatch, max_log_range):
    events = _events()
    compiled = _prepared(events, True, monkeypatch, max_log_range)
    eager = _prepared(events, False, monkeypatch, max_log_range)
    for name in FIELDS:
        a, b = getattr(compiled, name), getattr(eager, name)
        assert a.dtype == b.dtype and torch.equal(a, b), name
    assert torch.equal(compiled.rise, eager.rise) and compiled.row_bounds == eager.row_bounds
    hot = compiled.ignored.view(6, 9)
    if max_log_range is None:
        assert not bool(hot.any())
    else:  # the hot pixel and the one just over the limit, nothing else
        assert hot.nonzero().tolist() == [[0, 0], [2, 4]]
        at_hot = compiled.pixel == 0
        assert not bool(compiled.step[at_hot].any()) and not bool(compiled._after[at_hot].any())


def test_each_pixels_events_keep_their_order(monkeypatch):
    # a stable sort: within a pixel, events at equal times stay in the order given
    events = _events(seed=1)
    ci = _prepared(events, True, monkeypatch)
    order = ci.order.long()
    assert torch.equal(events.t[order], ci.t) and torch.equal(events.y[order] * 9 + events.x[order], ci.pixel)
    same_pixel = ci.pixel[1:] == ci.pixel[:-1]
    assert bool((order[1:][same_pixel] > order[:-1][same_pixel]).all())
    assert torch.equal(ci.run_start, torch.searchsorted(ci.pixel, torch.arange(54)))


def test_the_threads_split_the_events_and_not_the_result(monkeypatch):
    events = _events(seed=2)
    threads = torch.get_num_threads()
    monkeypatch.setattr("evlatcorr.compiled.event_runs._EVENTS_PER_WORKER", 100)  # several shares even for a few events
    monkeypatch.setattr("evlatcorr.compiled.event_runs._BLOCK", 4)
    try:
        torch.set_num_threads(1)
        one = _prepared(events, True, monkeypatch)
        torch.set_num_threads(3)
        three = _prepared(events, True, monkeypatch)
    finally:
        torch.set_num_threads(threads)
    for name in FIELDS:
        assert torch.equal(getattr(one, name), getattr(three, name)), name


def test_sort_into_runs_refuses_what_it_cannot_read():
    from evlatcorr.compiled.event_runs import sort_into_runs

    x, t, p = torch.zeros(3, dtype=torch.long), torch.zeros(3, dtype=torch.float64), torch.ones(3, dtype=torch.int8)
    with pytest.raises(ValueError, match="one length"):
        sort_into_runs(x, x[:2], t, p, (2, 2), 0.2, None)
    with pytest.raises(ValueError, match="t must be float64 and p int8"):
        sort_into_runs(x, x, t.float(), p, (2, 2), 0.2, None)
    with pytest.raises(ValueError, match="theta must be positive"):
        sort_into_runs(x, x, t, p, (2, 2), 0.0, None)
    with pytest.raises(ValueError, match="y must be a 1-D CPU tensor"):
        sort_into_runs(x, x.view(3, 1), t, p, (2, 2), 0.2, None)
