from __future__ import annotations

import pytest
import torch

from evlatcorr import Events
from evlatcorr.curves import (
    LatencyCurve,
    fit_latency_curve,
    light_off_latency,
    light_off_theory,
    main,
    plot_latency_curve,
    read_pairs_csv,
    simulate_light_off,
)

LEVELS = [0.1, 0.2, 0.4, 0.7, 1.0]


@pytest.fixture(scope="module")
def measured():
    events = simulate_light_off(LEVELS, seed=1, repetitions=3)
    assert [ev.batch_size for ev in events] == [3] * len(LEVELS)
    return torch.tensor([light_off_latency(ev, 2000.0) for ev in events], dtype=torch.float64)


def test_light_off_latency_by_hand():
    # two repetitions, switch at 1000 and 5000 us; OFF delays 100..400 and 300..600 (ON events ignored)
    t = torch.tensor([1100.0, 1200.0, 1300.0, 1400.0, 1050.0, 5300.0, 5400.0, 5500.0, 5600.0, 900.0])
    p = torch.tensor([-1, -1, -1, -1, 1, -1, -1, -1, -1, -1])
    b = torch.tensor([0, 0, 0, 0, 0, 1, 1, 1, 1, 0])
    ev = Events(torch.zeros(10, dtype=torch.long), torch.zeros(10, dtype=torch.long), t, p, b, sensor_size=(1, 1),
                sort=True)
    per = light_off_latency(ev, torch.tensor([1000.0, 5000.0]), fraction=0.5, reduce="none")
    torch.testing.assert_close(per, torch.tensor([150.0, 350.0], dtype=torch.float64))  # median of first 2 of 4
    assert light_off_latency(ev, [1000.0, 5000.0], fraction=0.5) == pytest.approx(250.0)
    assert light_off_latency(ev, [1000.0, 5000.0], fraction=0.01, reduce="none").tolist() == [100.0, 300.0]
    with pytest.raises(ValueError, match="one per repetition"):
        light_off_latency(ev, [1000.0, 2000.0, 3000.0])
    with pytest.raises(ValueError, match="reduce"):
        light_off_latency(ev, 1000.0, reduce="mean")


def test_light_off_latency_matches_photoreceptor_theory(measured):
    theory = torch.tensor([light_off_theory(level, 0.25, 0.2, (500.0, 10000.0)) for level in LEVELS])
    # the first 1% of OFF events come from the pixels with the lowest thresholds: a little early
    assert ((measured - theory).abs() / theory).max() < 0.12
    assert bool((measured[1:] <= measured[:-1] + 1e-6).all())  # latency falls as the light gets brighter


def test_fit_curve_from_csv_and_plot(measured, tmp_path):
    lux = torch.tensor(LEVELS, dtype=torch.float64) * 100  # any positive illuminance unit
    path = tmp_path / "pairs.csv"
    path.write_text("illuminance,latency_us\n" + "".join(f"{x},{y}\n" for x, y in zip(lux.tolist(),
                                                                                       measured.tolist())))
    x, y = read_pairs_csv(path)
    curve = fit_latency_curve(x, y, order=3)
    torch.testing.assert_close(curve(x), y, rtol=0.1, atol=50.0)
    plot_latency_curve(curve, x, y, tmp_path / "curve.png")
    assert (tmp_path / "curve.png").stat().st_size > 1000
    back = LatencyCurve.from_dict(curve.to_dict())
    torch.testing.assert_close(back(x), curve(x))


def test_command_line_fit(measured, tmp_path, capsys):
    path = tmp_path / "pairs.csv"
    path.write_text("illuminance,latency_us\n" + "".join(f"{x},{y}\n" for x, y in zip(LEVELS, measured.tolist())))
    main(["fit", str(path), "--order", "2", "--plot", str(tmp_path / "c.png"), "--out", str(tmp_path / "c.json")])
    assert "RMS residual" in capsys.readouterr().out
    import json

    data = json.loads((tmp_path / "c.json").read_text())
    assert len(data["coefficients"]) == 3 and data["rms_us"] < 300.0
    assert (tmp_path / "c.png").is_file()


def test_fit_exact_polynomial():
    lux = torch.logspace(-1, 3, 12, dtype=torch.float64)
    truth = fit_latency_curve(lux, torch.zeros(12), order=2)
    truth.coefficients = torch.tensor([300.0, 2000.0, 5000.0], dtype=torch.float64)
    fitted = fit_latency_curve(lux, truth(lux), order=2)
    torch.testing.assert_close(fitted.coefficients, truth.coefficients)


def test_errors(tmp_path):
    with pytest.raises(ValueError, match="order"):
        fit_latency_curve([1.0, 2.0], [1.0, 2.0], order=-1)
    with pytest.raises(ValueError, match="more than"):
        fit_latency_curve([1.0, 2.0], [1.0, 2.0], order=5)
    with pytest.raises(ValueError, match="positive"):
        fit_latency_curve([0.0, 2.0, 3.0], [1.0, 2.0, 3.0], order=1)
    bad = tmp_path / "bad.csv"
    bad.write_text("lux,ms\n1,2\n")
    with pytest.raises(ValueError, match="columns"):
        read_pairs_csv(bad)
    ev = Events(torch.zeros(1), torch.zeros(1), torch.tensor([5.0]), torch.tensor([1]), sensor_size=(1, 1))
    with pytest.raises(ValueError, match="no OFF events"):
        light_off_latency(ev, 0.0)
