from __future__ import annotations

import dataclasses
import json
import math

import pytest
import torch

from evlatcorr.benchmark.accuracy import (
    LATENCY_MODELS,
    MOTION_KINDS,
    Case,
    at_exposure,
    case_reference,
    corrector_estimator,
    evaluate_case,
    load_estimator,
    make_cases,
    run_suite,
    simulate_case,
    summarize,
    to_markdown,
    write_results,
)
from evlatcorr.benchmark.compare import edi_psnr
from evlatcorr.scenes import PROCEDURAL_SCENES
from evlatcorr.simulate import PHOTOGRAPHS_TEST, PHOTOGRAPHS_TRAIN

TINY = (32, 40)


def tiny_case(**changes) -> Case:
    """A small constant-latency case with a clear PSNR gap between ideal and delayed events."""
    case = Case(name="tiny", split="test", scene="checkerboard", scene_seed=5, dark_background=False, brightness=1.0,
                motion="translation", speed_px_per_ms=1.5, direction_deg=20.0, latency_model="constant",
                latency_us=4000.0, latency_range_us=(500.0, 6000.0), noise_rate_hz=0.0, leak_rate_hz=0.0,
                threshold_sigma=0.0, refractory_us=0.0, threshold=0.2, seed=3, size=TINY, exposure_us=10_000.0,
                after_us=8_000.0)
    return dataclasses.replace(case, **changes)


def scene_instances(cases: list[Case]) -> set[tuple[str, int | None]]:
    """(scene, seed) of every scene and sprite (seed None: a photograph)."""
    return {inst for c in cases for inst in ((c.scene, c.scene_seed), *c.objects)}


def test_cases_are_deterministic_and_named_uniquely():
    a, b = make_cases("test"), make_cases("test")
    assert a == b
    assert len({c.name for c in a}) == len(a)
    assert a[0].name.startswith("test-00-") and make_cases("test", num=5) == a[:5]
    assert all(c.size == (96, 128) for c in a) and make_cases("dev", size=(48, 64))[0].size == (48, 64)
    json.dumps([c.to_dict() for c in a])  # serialisable


def test_splits_are_disjoint():
    dev, test = make_cases("dev"), make_cases("test")
    assert not scene_instances(dev) & scene_instances(test)
    photos = {s for s, seed in scene_instances(test) if seed is None}
    assert photos <= set(PHOTOGRAPHS_TEST) and {s for s, seed in scene_instances(dev) if seed is None} <= set(
        PHOTOGRAPHS_TRAIN)
    assert not {c.seed for c in dev} & {c.seed for c in test}


@pytest.mark.parametrize("split, minimum", [("test", 48), ("dev", 40)])
def test_split_covers_every_factor(split, minimum):
    cases = make_cases(split)
    assert len(cases) >= minimum
    assert {c.latency_model for c in cases} == set(LATENCY_MODELS)
    assert {c.motion for c in cases} == set(MOTION_KINDS)
    assert set(PROCEDURAL_SCENES) <= {c.scene for c in cases if c.procedural}
    photographs = PHOTOGRAPHS_TEST if split == "test" else PHOTOGRAPHS_TRAIN
    assert {c.scene for c in cases if not c.procedural} == set(photographs)
    assert {m for c in cases for m in c.noise_models} == {"shot", "leak", "mismatch", "refractory"}
    assert any(c.brightness <= 0.1 for c in cases) and any(c.dark_regions for c in cases)
    assert any(c.scene == "shapes" and c.procedural and c.dark_background for c in cases)
    assert not any(c.dark_background and not c.procedural for c in cases)
    share = {m: sum(c.latency_model == m for c in cases) / len(cases) for m in LATENCY_MODELS}
    assert share["constant"] == pytest.approx(0.5, abs=0.05) and share["intensity"] == pytest.approx(0.25, abs=0.05)
    for c in cases:
        assert 0.03 <= c.brightness <= 1.0 and 0.2 <= c.speed_px_per_ms <= 4.0 and 0.15 <= c.threshold <= 0.3
        assert c.latency_model != "constant" or 200.0 <= c.latency_us <= 12000.0
        assert len(c.objects) == (2 if c.motion == "objects" else 0)


def test_bad_arguments():
    with pytest.raises(ValueError, match="split"):
        make_cases("validation")
    with pytest.raises(ValueError, match="num"):
        make_cases("dev", num=-1)
    with pytest.raises(ValueError, match="size"):
        make_cases("dev", size=(8, 8))
    with pytest.raises(ValueError, match="module:function"):
        load_estimator("no_colon")
    with pytest.raises(ValueError, match="not a callable"):
        load_estimator("evlatcorr.benchmark.accuracy:nothing_here")


@pytest.fixture(scope="module")
def tiny():
    case = tiny_case()
    simulated = simulate_case(case)
    return case, simulated, case_reference(case, simulated)


def test_simulate_case(tiny):
    case, (delayed, ideal, seq), ref = tiny
    assert delayed.batch_size == ideal.batch_size == 1 and delayed.sensor_size == TINY
    end = float(delayed.exposure_end[0])
    assert float(delayed.events.t.max()) < end + case.after_us and float(delayed.events.t.max()) > end + 7000.0
    assert seq.true_latency.unique().tolist() == [4000.0]
    assert ref["psnr_ideal"] > ref["psnr_uncorrected"] + 1.0  # a real gap to recover
    # the oracle scans 4000 µs too, so it is at least as close to the sharp frame as the true latency's EDI
    step = case.after_us / 240  # the scan's 60 steps up to where the events stop, halved twice
    assert ref["best_shift_us"] / step == pytest.approx(round(ref["best_shift_us"] / step))
    assert ref["psnr_best_shift"] >= edi_psnr(delayed, case.threshold, 4000.0) - 1e-3


def test_a_case_at_another_exposure_scales_its_latencies_and_the_oracles_reach():
    case = tiny_case(latency_model="intensity")
    longer = at_exposure(case, 20_000.0)
    assert longer.name == "tiny-e20ms" and longer.exposure_us == 20_000.0 and longer.after_us == 16_000.0
    assert longer.latency_us == 8000.0 and longer.latency_range_us == (1000.0, 12_000.0)
    assert (longer.scene, longer.speed_px_per_ms, longer.seed) == (case.scene, case.speed_px_per_ms, case.seed)
    with pytest.raises(ValueError, match="exposure_us must be a positive"):
        at_exposure(case, 0.0)
    # the oracle's scan ends where the case's events do: 4000 µs at a 5 ms exposure, on the 62.5 µs grid scaled
    short = at_exposure(tiny_case(), 5000.0)
    ref = case_reference(short, simulate_case(short))
    assert 0.0 <= ref["best_shift_us"] <= 4000.0 and abs(ref["best_shift_us"] - 2000.0) <= 500.0


@pytest.mark.parametrize("motion", ["objects", "rotation", "zoom", "random"])
def test_every_motion_kind_simulates(motion):
    case = next(c for c in make_cases("test", size=TINY) if c.motion == motion)
    case = dataclasses.replace(case, exposure_us=4000.0, after_us=3000.0, latency_model="constant", latency_us=1000.0)
    delayed, ideal, seq = simulate_case(case)
    assert len(delayed.events) > 0 and len(ideal.events) > 0 and delayed.sensor_size == TINY
    assert (seq.config["objects"] is not None) == (motion == "objects")
    if motion == "objects":
        assert [o["sprite"] for o in seq.config["objects"]] == [s if k is None else [s, k] for s, k in case.objects]


def test_oracle_and_zero_estimators(tiny):
    case, simulated, ref = tiny
    oracle = evaluate_case(case, lambda f: f.meta["true_latency"], simulated=simulated, reference=ref)
    assert oracle["latency_error_us"] == 0.0 and oracle["recovery"] == pytest.approx(1.0, abs=0.02)
    assert oracle["psnr_corrected"] == pytest.approx(oracle["psnr_ideal"], abs=0.05)
    zero = evaluate_case(case, lambda f: torch.zeros(1, 1, *TINY), simulated=simulated, reference=ref)
    assert zero["recovery"] == pytest.approx(0.0, abs=1e-6) and zero["latency_error_us"] == -4000.0
    assert not zero["no_gap"] and zero["time_s"] >= 0.0
    scalar = evaluate_case(case, lambda f: 4000.0, simulated=simulated, reference=ref)  # scalars are broadcast
    assert scalar["recovery"] == pytest.approx(oracle["recovery"])
    assert scalar["name"] == "tiny" and scalar["noise_models"] == ""
    with pytest.raises(ValueError, match="latency map"):
        evaluate_case(case, lambda f: torch.zeros(2, 2), simulated=simulated, reference=ref)


@pytest.mark.parametrize("model", ["intensity", "intensity_delay"])
def test_latency_varying_with_intensity_has_a_best_shift_oracle(model):
    # no one latency is true: the best constant shift is what constant correction can reach at most
    case = tiny_case(latency_model=model, latency_us=0.0, brightness=0.3, noise_rate_hz=2.0, leak_rate_hz=0.5,
                     refractory_us=100.0, threshold_sigma=0.05)
    simulated = simulate_case(case)
    result = evaluate_case(case, lambda f: torch.full((1, 1, *TINY), 2000.0), simulated=simulated)
    step = case.after_us / 240  # the scan's 60 steps up to where the events stop, halved twice
    assert result["best_shift_us"] / step == pytest.approx(round(result["best_shift_us"] / step))
    # 0 and 2000 µs are among the scanned shifts (every 133 µs): the oracle is at least as good as either
    assert result["psnr_best_shift"] >= result["psnr_uncorrected"] - 1e-3
    assert result["psnr_best_shift"] >= result["psnr_corrected"] - 1e-3
    true = simulated[0].meta["true_latency"]
    assert float(true.max()) > float(true.min())  # a map
    assert result["latency_error_us"] == pytest.approx(float((2000.0 - true).abs().mean()), rel=1e-4)
    gain = result["psnr_best_shift"] - result["psnr_uncorrected"]
    if gain > 0.1:
        want = (result["psnr_corrected"] - result["psnr_uncorrected"]) / gain
        assert result["best_shift_share"] == pytest.approx(want) and result["best_shift_share"] <= 1.0 + 1e-3
    else:
        assert math.isnan(result["best_shift_share"])


def test_summary_and_files(tiny, tmp_path):
    case, simulated, ref = tiny
    rows = []
    for name, fn in (("constant", lambda f: f.meta["true_latency"]), ("spatial", lambda f: torch.zeros(1, 1, *TINY))):
        for c in (case, dataclasses.replace(case, name="tiny-map", latency_model="intensity_delay")):
            row = evaluate_case(c, fn, simulated=simulated, reference=ref)
            row["estimator"] = name
            rows.append(row)
    summary = summarize(rows)
    groups = {(g["estimator"], g["latency_model"]): g for g in summary["groups"]}
    assert groups[("constant", "constant")]["median_abs_error_us"] == 0.0
    assert groups[("constant", "constant")]["median_best_shift_error_us"] == abs(ref["best_shift_us"] - 4000.0)
    assert groups[("spatial", "constant")]["worst_recovery"] == pytest.approx(0.0, abs=1e-6)
    assert groups[("constant", "all")]["cases"] == 2
    assert [c["spatial_better"] for c in summary["spatial_vs_constant"]] == [False]
    text = to_markdown(rows, summary)
    assert "| constant | tiny |" in text and "Spatial vs constant" in text and "worst abs error with a gap" in text
    paths = write_results(rows, tmp_path / "out", summary, header="# title\n\n")
    assert paths["md"].read_text().startswith("# title")
    data = json.loads(paths["json"].read_text())
    assert len(data["results"]) == 4 and data["summary"]["groups"]
    assert paths["csv"].read_text().count("\n") == 5
    assert paths["png"].read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"  # the figure, beside the tables


def test_the_figure_is_refused_without_an_estimate_and_not_written(tmp_path):
    from evlatcorr.benchmark.accuracy_figure import plot_results

    failed = {"estimator": "e", "split": "test", "name": "case-0", "latency_model": "constant", "error": "boom",
              "est_latency_us": math.nan}
    with pytest.raises(ValueError, match="no estimates to draw"):
        plot_results([failed], tmp_path / "results.png")


def test_the_worst_error_is_also_reported_over_the_cases_where_latency_changes_the_image():
    # a smooth gradient's latency changes nothing EDI shows (no gap): its error counts in the worst error, not in the
    # worst error with a gap, as it does not count in the recoveries
    rows = [{"latency_model": "constant", "latency_abs_error_us": error, "no_gap": no_gap, "recovery": recovery,
             "best_shift_us": 0.0, "true_latency_us": 0.0, "best_shift_share": 1.0, "time_s": 0.1,
             "estimator": "e", "split": "test", "name": f"case-{k}"}
            for k, (error, no_gap, recovery) in enumerate(((8630.0, True, math.nan), (1651.0, False, 0.48),
                                                           (300.0, False, 0.97)))]
    (group, _) = summarize(rows)["groups"]
    assert group["worst_abs_error_us"] == 8630.0 and group["worst_abs_error_with_gap_us"] == 1651.0
    assert group["worst_recovery"] == 0.48 and group["no_gap"] == 1


def test_the_learned_readers_spread_is_reported_and_banded(tiny):
    case, simulated, ref = tiny
    # the built-in corrector returns its frames: the suite reads the latency and the reader's spread
    row = evaluate_case(case, corrector_estimator("constant", threshold=case.threshold), simulated=simulated,
                        reference=ref)
    assert row["latency_spread_us"] > 0.0
    # a bare latency map has no spread
    assert math.isnan(evaluate_case(case, lambda f: f.meta["true_latency"], simulated=simulated,
                                    reference=ref)["latency_spread_us"])
    # six cases of known spread and error: three bands of two, from the least spread on
    rows = [dict(row, estimator="e", latency_spread_us=float(k), latency_abs_error_us=float(e))
            for k, e in enumerate([100.0, 300.0, 900.0, 700.0, 5000.0, 2500.0])]
    bands = summarize(rows)["spread_bands"]
    assert [(b["band"], b["cases"], b["spread_low_us"], b["spread_high_us"]) for b in bands] == [
        (1, 2, 0.0, 1.0), (2, 2, 2.0, 3.0), (3, 2, 4.0, 5.0)]
    assert [b["median_abs_error_us"] for b in bands] == [200.0, 800.0, 3750.0]
    assert [b["over_2ms"] for b in bands] == [0, 0, 2] and bands[2]["worst_abs_error_us"] == 5000.0
    assert "spread against the error" in to_markdown(rows, summarize(rows))


def test_the_estimate_on_ideal_events_is_reported(tiny):
    case, simulated, ref = tiny
    # an estimator that returns the true latency gives 0 on the ideal events (their true latency is 0)
    row = evaluate_case(case, lambda f: f.meta["true_latency"], simulated=simulated, reference=ref)
    assert row["ideal_estimate_us"] == 0.0
    late = evaluate_case(case, lambda f: torch.full((1, 1, *TINY), 300.0), simulated=simulated, reference=ref)
    assert late["ideal_estimate_us"] == 300.0
    group = next(g for g in summarize([dict(row, estimator="e"), dict(late, estimator="e")])["groups"]
                 if g["latency_model"] == "all")
    assert (group["ideal_cases"], group["ideal_within_150us"], group["worst_ideal_estimate_us"]) == (2, 1, 300.0)
    assert group["median_ideal_estimate_us"] == 150.0
    assert "Ideal events (no latency)" in to_markdown([dict(row, estimator="e")])


def test_frames_can_keep_the_events_from_before_the_exposure():
    case = tiny_case()
    plain, plain_ideal, _ = simulate_case(case)
    delayed, ideal, _ = simulate_case(case, before_us=1000.0)
    start = float(plain.exposure_start[0])
    # the same simulation: the same frames, and the same events from the exposure start on
    assert torch.equal(delayed.blurry, plain.blurry) and torch.equal(delayed.exposure_start, plain.exposure_start)
    for early, late in ((delayed, plain), (ideal, plain_ideal)):
        assert start - 1000.0 <= float(early.events.t.min()) < start
        assert torch.equal(early.events.t[early.events.t >= start], late.events.t)
    with pytest.raises(ValueError, match="before_us"):
        simulate_case(case, before_us=case.after_us + 1.0)
    # the suite hands the estimators such frames
    seen = []
    run_suite([case], {"e": lambda c: lambda f: seen.append(float(f.events.t.min())) or f.meta["true_latency"]},
              progress=None, before_us=1000.0)
    assert seen and all(start - 1000.0 <= t < start for t in seen)


def test_what_correcting_ideal_events_costs_is_reported(tiny):
    case, simulated, ref = tiny
    ideal = simulated[1]
    # no shift costs nothing; a shift costs what EDI of the ideal events at that shift loses
    row = evaluate_case(case, lambda f: f.meta["true_latency"], simulated=simulated, reference=ref)
    assert row["ideal_psnr_change_db"] == 0.0
    late = evaluate_case(case, lambda f: torch.full((1, 1, *TINY), 3000.0), simulated=simulated, reference=ref)
    assert late["ideal_psnr_change_db"] == pytest.approx(edi_psnr(ideal, case.threshold, 3000.0) - ref["psnr_ideal"])
    assert late["ideal_psnr_change_db"] < -0.5  # a 3 ms shift of a moving scene's events blurs it
    rows = [dict(row, estimator="e", ideal_psnr_change_db=v) for v in (0.5, -1.0, -3.0, 0.0)]
    group = next(g for g in summarize(rows)["groups"] if g["latency_model"] == "all")
    assert group["mean_ideal_psnr_change_db"] == pytest.approx(-0.875)
    assert (group["worst_ideal_psnr_change_db"], group["ideal_losing_half_db"]) == (-3.0, 2)
    assert "-0.88 / -3.00 / -3.00 | 2 |" in to_markdown(rows)
    # an estimator that fails on the ideal events leaves both columns NaN, not the case
    def fails_on_ideal(frames):
        if frames.meta["true_latency"].abs().max() == 0:
            raise ValueError("no")
        return frames.meta["true_latency"]
    failed = evaluate_case(case, fails_on_ideal, simulated=simulated, reference=ref)
    assert math.isnan(failed["ideal_estimate_us"]) and math.isnan(failed["ideal_psnr_change_db"])
    assert not failed["error"]


def test_an_estimator_that_raises_fails_its_case_not_the_suite(tiny, tmp_path):
    case, simulated, ref = tiny

    def no_events(frames):
        raise ValueError("sample 0 has no events")

    failed = evaluate_case(case, no_events, simulated=simulated, reference=ref)
    assert failed["error"] == "ValueError: sample 0 has no events"
    assert math.isnan(failed["est_latency_us"]) and math.isnan(failed["recovery"]) and not failed["no_gap"]
    assert failed["psnr_ideal"] == ref["psnr_ideal"]  # the reference still reported
    good = evaluate_case(case, lambda f: f.meta["true_latency"], simulated=simulated, reference=ref)
    assert good["error"] == ""
    rows = [dict(failed, estimator="e"), dict(good, estimator="e")]
    group = next(g for g in summarize(rows)["groups"] if g["latency_model"] == "constant")
    # the failure is counted, and left out of the figures the other case sets
    assert group["failed"] == 1 and group["worst_abs_error_us"] == 0.0 and group["cases"] == 2
    assert "failed: ValueError: sample 0 has no events" in to_markdown(rows)
    lines = []
    run_suite([case], {"e": lambda c: no_events}, progress=lines.append)
    assert lines == ["[1/1]        e tiny: the estimator failed (ValueError: sample 0 has no events)"]


def test_load_estimator_from_a_file(tmp_path):
    path = tmp_path / "my_estimator.py"
    path.write_text("import torch\n\ndef estimate(frames):\n    return torch.zeros(frames.batch_size)\n")
    fn = load_estimator(f"{path}:estimate")
    assert callable(fn) and fn.__name__ == "estimate"
    assert load_estimator("evlatcorr.benchmark.accuracy:make_cases") is make_cases


def test_the_accuracy_script_writes_its_tables_and_groups_its_warnings(tmp_path):
    from tests.commands import run_script

    run = run_script("accuracy.py", "--split", "dev", "--num", "2", "--size", "32", "40", "--mode", "constant",
                     "--out", str(tmp_path), cwd=tmp_path)
    assert run.returncode == 0, run.stderr
    table = (tmp_path / "results.md").read_text()
    assert "## Summary" in table and (tmp_path / "results.csv").is_file()
    # the warning every case raises by design (its stream stops 15 ms after the exposure) is one kind, not one a case
    assert "- 2 of 2 estimates raised warnings, of " in table
    kinds = [line for line in table.splitlines() if line.startswith('  - 2 estimates: "events of sample 0 end at')]
    assert len(kinds) == 1


@pytest.mark.parametrize(("flags", "expected"), [([], "number"), (["--auto-threshold"], "auto")])
def test_an_extra_estimator_is_handed_auto_as_the_threshold_with_auto_threshold(tmp_path, flags, expected):
    from tests.commands import run_script

    # the estimator fails its case unless it sees the threshold it is promised: the error lands in the csv
    path = tmp_path / "threshold_check.py"
    path.write_text("import torch\n\ndef estimate(frames):\n"
                    "    seen = 'auto' if frames.meta['threshold'] == 'auto' else 'number'\n"
                    f"    assert seen == {expected!r}, seen\n"
                    "    return torch.zeros(frames.batch_size)\n")
    run = run_script("accuracy.py", "--split", "dev", "--num", "1", "--size", "32", "40", "--mode", "none",
                     "--estimator", f"{path}:estimate", *flags, "--out", str(tmp_path), cwd=tmp_path)
    assert run.returncode == 0, run.stderr
    assert "the estimator failed" not in run.stdout


def test_warning_kinds_counts_the_estimates_raising_each_kind_and_refuses_rows_without_messages():
    from evlatcorr.benchmark.accuracy import warning_kinds

    rows = [{"warnings": ["latency 1200 us at the edge", "no minimum"]}, {"warnings": ["latency -30.5 us at the edge"]},
            {"warnings": []}]
    assert warning_kinds(rows) == [(2, "latency 1200 us at the edge"), (1, "no minimum")]
    with pytest.raises(ValueError, match="row 1"):
        warning_kinds([{"warnings": []}, {"error": ""}])

