import math

import pytest

from evlatcorr.benchmark.accuracy import make_cases
from evlatcorr.benchmark.sequences import IDEAL, LOSING_DB, evaluate_sequence, summarize_sequences
from evlatcorr.temporal import DEFAULT_PAIR_REFINE


@pytest.fixture(scope="module")
def all_rows():
    # the first constant-latency dev case at 48x64, as 3 back-to-back frames, and its ideal events
    case = next(c for c in make_cases("dev", size=(48, 64)) if c.latency_model == "constant")
    return case, evaluate_sequence(case, num_frames=3, windows={"fused ±1": (1, 1)})


@pytest.fixture(scope="module")
def rows(all_rows):
    case, rows = all_rows
    return case, [r for r in rows if r["model"] != IDEAL]


def test_every_frame_is_scored_with_its_own_and_the_fused_latency(rows):
    case, rows = rows
    assert {r["estimate"] for r in rows} == {"per frame", "fused ±1"}
    frames = sorted({r["frame"] for r in rows})
    assert frames == [0, 1, 2] and len(rows) == 2 * len(frames)
    for r in rows:
        assert r["true_latency_us"] == pytest.approx(case.latency_us)
        assert r["error_us"] == pytest.approx(r["latency_us"] - r["true_latency_us"])
        gap = r["psnr_ideal"] - r["psnr_uncorrected"]
        if gap > 0.1:
            assert r["recovery"] == pytest.approx((r["psnr_corrected"] - r["psnr_uncorrected"]) / gap)
        else:
            assert math.isnan(r["recovery"])


def test_the_summary_counts_frames_per_estimate_and_model(rows):
    _, rows = rows
    summary = summarize_sequences(rows)
    for estimate in ("per frame", "fused ±1"):
        stats = summary[estimate]["constant"]
        assert stats["frames"] == 3
        errors = sorted(abs(r["error_us"]) for r in rows if r["estimate"] == estimate)
        assert stats["median_abs_error_us"] == pytest.approx(errors[1]) and stats["worst_abs_error_us"] == errors[2]


def test_the_ideal_events_are_estimated_too_and_scored_by_what_correcting_them_costs(all_rows):
    case, rows = all_rows
    ideal = [r for r in rows if r["model"] == IDEAL]
    assert {r["estimate"] for r in ideal} == {"per frame", "fused ±1"} and len(ideal) == 6
    for r in ideal:
        assert r["true_latency_us"] == 0.0 and r["error_us"] == r["latency_us"]
        assert r["psnr_uncorrected"] == r["psnr_ideal"] and math.isnan(r["recovery"])
        assert r["latency_us"] > 0.0 or r["psnr_corrected"] == pytest.approx(r["psnr_ideal"])
    stats = summarize_sequences(rows)["per frame"][IDEAL]
    alone = [r for r in ideal if r["estimate"] == "per frame"]
    changes = [r["psnr_corrected"] - r["psnr_ideal"] for r in alone]
    assert stats["frames"] == 3 and stats["within_150us"] == sum(abs(r["latency_us"]) <= 150.0 for r in alone)
    assert stats["mean_psnr_change_db"] == pytest.approx(sum(changes) / 3)
    assert stats["worst_psnr_change_db"] == min(changes)
    assert stats["losing_frames"] == sum(c < -LOSING_DB for c in changes)
    without = evaluate_sequence(case, num_frames=3, windows={"fused ±1": (1, 1)}, ideal=False)
    key = [(r["estimate"], r["frame"], r["latency_us"], r["psnr_corrected"]) for r in rows if r["model"] != IDEAL]
    assert [(r["estimate"], r["frame"], r["latency_us"], r["psnr_corrected"]) for r in without] == key


def test_fused_against_own_averages_frames_within_a_case_first():
    from evlatcorr.benchmark.sequences import fused_against_own

    rows = []
    for case, changes in (("a", [3.0, 3.0, 3.0, 3.0]), ("b", [0.0]), ("c", [-0.6, -0.6])):
        for frame, change in enumerate(changes):
            rows += [dict(case=case, model="constant", frame=frame, estimate="per frame", psnr_corrected=30.0),
                     dict(case=case, model="constant", frame=frame, estimate="fused", psnr_corrected=30.0 + change)]
    rows.append(dict(case="d", model="constant", frame=0, estimate="fused", psnr_corrected=99.0))  # no own estimate
    (group,) = fused_against_own(rows)
    # case means 3, 0 and -0.6: their mean, not the frames' (which would weigh case a four times)
    assert (group["cases"], group["frames"]) == (3, 7)
    assert group["mean_psnr_change_db"] == pytest.approx(0.8)
    assert (group["cases_gaining"], group["cases_losing"]) == (1, 1)
    assert group["psnr_change_low_db"] <= 0.8 <= group["psnr_change_high_db"]


def test_a_sequence_needs_at_least_one_frame():
    with pytest.raises(ValueError, match="num_frames"):
        evaluate_sequence(make_cases("dev")[0], num_frames=0)
    for kwargs, match in ((dict(pair_weights=(10.0, 0.0)), "pair_weights must be positive"),
                          (dict(frame_gap=0.5), "frame_gap must be 1 or more"),
                          (dict(ramp_us=-1.0), "ramp_us must be 0 or more"),
                          (dict(ramp_next_factor=0.0), "ramp_next_factor must be positive or None"),
                          (dict(pair_refines=(0.5,)), "pair_refines must be numbers >= 1"),
                          (dict(pair_refines=()), "pair_refines must be numbers >= 1")):
        with pytest.raises(ValueError, match=match):
            evaluate_sequence(make_cases("dev")[0], **kwargs)


def test_the_script_writes_its_table(tmp_path):
    import json

    from tests.commands import ROOT, run_script

    script = ["sequence_accuracy.py", "--split", "dev", "--num", "6", "--size", "32", "40", "--frames", "2",
              "--models", "constant", "--no-latency-mass", "0.3", "--out", str(tmp_path)]
    run = run_script(*script, cwd=ROOT)
    assert run.returncode == 0, run.stderr
    table = (tmp_path / "results.md").read_text()
    for estimate in ("per frame", "fused ±2", "fused, past 2 (stream)", "fused ±2, 0 where p(0) > 0.3",
                     "fused ±2, pairs 10", "fused, past 2 (stream), pairs 10"):  # each pair's agreement too
        assert f"| {estimate} | constant latency |" in table
    summary = json.loads((tmp_path / "results.json").read_text())["summary"]
    assert summary["per frame"]["constant"]["frames"] == 2  # the one constant case among the first six, 2 frames
    rows = (tmp_path / "results.csv").read_text().splitlines()
    assert rows[0].startswith("case,model,frame,estimate") and len(rows) == 1 + 2 * 7 * 2  # and the ideal events'
    assert "| fused ±2 | 2 |" in table  # the ideal events' table
    # each fused estimate against the frames' own, case by case (one case here: no interval)
    paired = json.loads((tmp_path / "results.json").read_text())["fused_against_own"]
    assert {(g["estimate"], g["model"], g["cases"], g["frames"]) for g in paired} >= {
        ("fused ±2", "constant", 1, 2), ("fused ±2", IDEAL, 1, 2)}
    assert "| fused ±2 | constant latency | 1 (2) |" in table and "(– to –)" in table
    bad = run_script(*script[:-2], "--frames", "1", cwd=ROOT)
    assert bad.returncode == 2
    assert "--frames must be at least 2 (fusing needs a frame's neighbours), got 1" in bad.stderr
    bad = run_script(*script[:-2], "--no-latency-mass", "1", cwd=ROOT)
    assert bad.returncode == 2 and "--no-latency-mass must be in [0, 1)" in bad.stderr
    for option, value, message in (("--pair-weights", "0", "--pair-weights must be positive"),
                                   ("--frame-gap", "0.5", "--frame-gap must be 1 or more"),
                                   ("--pair-ramp-us", "-1", "--pair-ramp-us must be 0 or more"),
                                   ("--pair-ramp-next", "-1", "--pair-ramp-next must be 0 or more"),
                                   ("--pair-refine", "0.5", "--pair-refine must be 1 or more")):
        bad = run_script(*script[:-2], option, value, cwd=ROOT)
        assert bad.returncode == 2 and message in bad.stderr


def test_each_pairs_agreement_is_fused_at_each_weight_with_a_cameras_gap():
    # the first constant-latency dev case (7.34 ms) as 3 frames 1.25 exposures apart: the first two have a next one
    case = next(c for c in make_cases("dev", size=(48, 64)) if c.latency_model == "constant")
    rows = evaluate_sequence(case, num_frames=3, windows={}, ideal=False, pair_weights=(10.0, 30.0), frame_gap=1.25)
    assert [r["estimate"] for r in rows if r["frame"] == 0] == [
        "per frame", "fused ±2, pairs 10", "per frame, with its pair 10", "fused, past 2 (stream), pairs 10",
        "fused ±2, pairs 30", "per frame, with its pair 30", "fused, past 2 (stream), pairs 30"]
    fused = [r["latency_us"] for r in rows if r["estimate"] == "fused ±2, pairs 10"]
    assert len(fused) == 3 and all(abs(v - case.latency_us) < 1000.0 for v in fused), (case.latency_us, fused)
    assert [r["latency_us"] for r in rows if r["estimate"] == "fused ±2, pairs 30"] != fused


def test_the_pairs_refinement_is_scored_at_each_factor_the_default_under_its_own_name():
    # --pair-refine 10 1: the default (10, the estimates' plain names) and no refinement (", refine 1"), each as
    # fuse_latencies gives it from the same frames' evidence
    case = next(c for c in make_cases("dev", size=(48, 64)) if c.latency_model == "constant")
    rows = evaluate_sequence(case, num_frames=3, windows={}, ideal=False, pair_weights=(10.0,),
                             pair_refines=(DEFAULT_PAIR_REFINE, 1.0))
    assert [r["estimate"] for r in rows if r["frame"] == 0] == [
        "per frame", "fused ±2, pairs 10", "per frame, with its pair 10", "fused, past 2 (stream), pairs 10",
        "fused ±2, pairs 10, refine 1", "per frame, with its pair 10, refine 1",
        "fused, past 2 (stream), pairs 10, refine 1"]
    plain = evaluate_sequence(case, num_frames=3, windows={}, ideal=False, pair_weights=(10.0,), pair_refines=(None,))
    assert [r["latency_us"] for r in rows if r["estimate"] == "fused ±2, pairs 10, refine 1"] == [
        r["latency_us"] for r in plain if r["estimate"] == "fused ±2, pairs 10, refine 1"]
    assert [r["latency_us"] for r in rows if r["estimate"] == "fused ±2, pairs 10"] == [
        r["latency_us"] for r in evaluate_sequence(case, num_frames=3, windows={}, ideal=False, pair_weights=(10.0,))
        if r["estimate"] == "fused ±2, pairs 10"]


def test_the_sequences_slope_over_intensity_is_scored_beside_the_fused_latency():
    # --slope: one curve fitted to all the sequence's pairs; a constant-latency sequence shows no slope, so the
    # sloped rows are the fused ones; a per-pixel delay sequence's maps spread, their mean the row's latency
    constant = next(c for c in make_cases("dev", size=(48, 64)) if c.latency_model == "constant")
    rows = evaluate_sequence(constant, num_frames=3, windows={}, ideal=False, pair_weights=(10.0,), slope=True)
    fused = [r for r in rows if r["estimate"] == "fused ±2, pairs 10"]
    sloped = [r for r in rows if r["estimate"] == "fused ±2, pairs 10, sloped"]
    assert len(sloped) == len(fused) == 3
    for a, b in zip(fused, sloped):
        assert {k: v for k, v in a.items() if k != "estimate"} == {k: v for k, v in b.items() if k != "estimate"}
    assert not any(r["estimate"].endswith("sloped") for r in evaluate_sequence(
        constant, num_frames=3, windows={}, ideal=False, pair_weights=(10.0,)))


def test_a_case_the_simulator_refuses_is_left_out_and_named(tmp_path):
    from tests.commands import ROOT, run_script

    # at 40 ms, six frames of dev-13's zoom compound past any photograph: that case is named, the others reported
    run = run_script("sequence_accuracy.py", "--split", "dev", "--num", "14", "--size", "32", "40", "--frames", "6",
                     "--models", "constant", "--no-ideal", "--exposure-us", "40000", "--out", str(tmp_path), cwd=ROOT)
    assert run.returncode == 0, run.stderr
    table = (tmp_path / "results.md").read_text()
    assert "1 case(s) not simulated, left out: dev-13-proc-gradient-dark-b0.14-zoom3.2-const9000-e40ms (the motion" \
        in table
    assert "| per frame | constant latency | 24 (" in table  # the other four cases, six frames each
