"""``benchmarks/speed.py --part against``: this checkout's default search timed against a git revision's."""

from __future__ import annotations

import subprocess

import pytest

from tests.commands import ROOT, run_script

pytestmark = pytest.mark.skipif(not (ROOT / ".git").exists(), reason="needs a git checkout (it reads a revision)")


def run_speed(*args: str) -> subprocess.CompletedProcess:
    return run_script("speed.py", "--part", "against", *args, cwd=ROOT)


def test_against_a_revision_times_both_in_turn_with_one_score_and_prints_the_ratio():
    # each round starts a process for each side: one run checks the order, the score given to both, and the ratio
    run = run_speed("--against", "HEAD", "--height", "24", "--width", "32", "--repeats", "1", "--rounds", "2",
                    "--score", "consensus")
    assert run.returncode == 0, run.stderr
    lines = run.stdout.splitlines()
    assert [line.split(":")[0] for line in lines if line.startswith("[cpu] round")] == [
        "[cpu] round 1, this checkout", "[cpu] round 1, HEAD", "[cpu] round 2, this checkout", "[cpu] round 2, HEAD"]
    summary = next(line for line in lines if "medians of 2 calls" in line)
    assert summary.startswith("[cpu] search with score='consensus': this checkout")
    # HEAD's search is this checkout's (the tests do not change it): the same estimate on the same frame
    estimates = summary.split("estimates ")[1].split(" us")[0].split(" and ")
    assert estimates[0] == estimates[1]
    assert float(lines[-1].split("speed-up against HEAD: ")[1].rstrip("x")) > 0


@pytest.mark.parametrize("args, code, message", [
    (("--against", "no-such-revision-xyz"), 1, "cannot read revision 'no-such-revision-xyz'"),
    ((), 2, "--part against needs --against REV"),
])
def test_against_bad_arguments_exit_with_one_clear_line(args, code, message):
    run = run_speed(*args)
    assert run.returncode == code and message in run.stderr
    assert "Traceback" not in run.stderr


def test_stages_add_up_to_the_whole_search_compiled_and_eager_with_and_without_the_tiles():
    run = run_script("speed.py", "--part", "stages", "--height", "24", "--width", "32",
                          "--repeats", "1", cwd=ROOT)
    assert run.returncode == 0, run.stderr
    lines = run.stdout.splitlines()
    headers = [k for k, line in enumerate(lines) if " by stage" in line]
    tiled, whole = "the whole frame and its tiles", "the whole frame alone (tiles=False)"
    assert [lines[k].split("by stage, ")[1].split(", ")[:2] for k in headers] == [
        ["compiled", tiled], ["compiled", whole], ["eager", tiled], ["eager", whole]]
    for k in headers:
        end = next(j for j in range(k + 1, len(lines)) if lines[j].startswith("[cpu]   total"))
        times = {line.split(": ")[0].removeprefix("[cpu]   "): float(line.split(": ")[1].split(" ms")[0])
                 for line in lines[k + 1:end + 1]}
        reductions = ("sharpness scores", "ghost moments", "overshoots")
        expected = [f"{r}, whole frame and tiles" for r in reductions] if tiled in lines[k] else list(reductions)
        assert set(expected) <= set(times) and {"read the candidates' windows", "other", "total"} <= set(times)
        assert all(value >= 0 for value in times.values())
        parts = sum(value for label, value in times.items() if label != "total")
        assert parts == pytest.approx(times["total"], abs=0.5)  # each printed to 0.1 ms
    ratios = [line for line in lines if "tiles/whole frame alone" in line]
    assert len(ratios) == 2 and all(float(line.split(": ")[1].removesuffix("x")) > 0 for line in ratios)
    assert float(lines[-1].split("eager/compiled: ")[1].removesuffix("x")) > 0


def test_batch_part_times_each_batch_size_against_one_frame():
    run = run_script("speed.py", "--part", "batch", "--height", "24", "--width", "32",
                          "--repeats", "1", "--batch-sizes", "3", "1", "2", "--device", "cpu", cwd=ROOT)
    assert run.returncode == 0, run.stderr
    lines = [line for line in run.stdout.splitlines() if line.startswith("[cpu]")]
    assert "one frame" in lines[0] and "frames/s" in lines[0]
    assert [line.split(" frames in one call")[0] for line in lines[1:]] == ["[cpu] 2", "[cpu] 3"]
    assert all("x one frame" in line and line.endswith("frames/s") for line in lines[1:])


def test_batch_sizes_must_be_positive():
    run = run_script("speed.py", "--part", "batch", "--batch-sizes", "0", cwd=ROOT)
    assert run.returncode == 2 and "--batch-sizes must be positive" in run.stderr


def test_stream_part_times_the_streaming_corrector_against_the_corrector_alone():
    run = run_script("speed.py", "--part", "stream", "--adapter-size", "24", "32", "--repeats",
                          "1", "--device", "cpu", cwd=ROOT)
    assert run.returncode == 0, run.stderr
    line = next(line for line in run.stdout.splitlines() if line.startswith("[cpu] stream of 8 frames at 32x24"))
    assert float(line.split("stream/alone: ")[1]) > 0


def test_recording_times_the_corrector_compiled_and_eager(tmp_path):
    from evlatcorr.io import write_sequence
    from evlatcorr.simulate import simulate

    recording = tmp_path / "rec.h5"
    write_sequence(recording, simulate("camera", num_frames=2, height=24, width=32, latency_us=2000.0, seed=1))
    args = ["--part", "recording", "--recording"]
    run = run_script("speed.py", *args, str(recording), "--threshold", "0.2", "--repeats", "1", cwd=ROOT)
    assert run.returncode == 0, run.stderr
    lines = run.stdout.splitlines()
    assert lines[0].startswith("[cpu] rec.h5: 2 frames 32x24")
    assert "compiled passes: " in lines[1] and "ms per frame; eager: " in lines[1] and "speed-up" in lines[1]
    assert float(lines[2].split(": ")[1].split(" us")[0]) < 1.0  # the same latencies either way
    assert lines[3].startswith("[cpu] each pair's agreement (pair_log_odds, 1 pairs, 101 candidates): ")
    assert float(lines[3].split("candidates): ")[1].split(" ms per pair")[0]) > 0 and "x the corrector's" in lines[3]
    assert lines[4].startswith("[cpu] the recording's θ") and lines[4].endswith(" s (once)")
    missing = run_script("speed.py", *args, str(tmp_path / "no.h5"), cwd=ROOT)
    assert missing.returncode == 1 and "no such file" in missing.stderr


def test_profile_lists_the_search_operators_on_a_cpu():
    run = run_script("profile_search.py", "--device", "cpu", "--height", "24", "--width", "32",
                          "--calls", "1", "--rows", "5", "--by-line", cwd=ROOT)
    assert run.returncode == 0, run.stderr
    head = next(line for line in run.stdout.splitlines() if line.startswith("[cpu] default search"))
    assert "1 frame(s) per call" in head and "24x32" in head and "ms per call" in head
    assert "Self CPU" in run.stdout  # the operators' table
    by_line = run.stdout.split("each a kernel or a copy):\n")[1].splitlines()[:5]
    # on a CPU no operator takes a tensor off the host
    assert all(float(row.split()[0]) > 0 and " 0.0 off host " in row and "evlatcorr/" in row
               for row in by_line), by_line


def test_profile_counts_the_reductions_kernels_as_a_gpu_takes_them_without_one():
    run = run_script("profile_search.py", "--reductions", "--height", "36", "--width", "48", cwd=ROOT)
    assert run.returncode == 0, run.stderr
    assert "1 frame(s) of 36x48, 101 candidates" in run.stdout and "meta tensors" in run.stdout
    counts = {line.split(":")[0].strip(): int(line.split(":")[1]) for line in run.stdout.splitlines()[1:]}
    # the tiles add their own kernels, fewer than the whole frame's reductions take (334 against 125 before they were
    # written for a GPU)
    assert set(counts) == {"whole frame", "whole frame and tiles"}
    assert 0 < counts["whole frame"] < counts["whole frame and tiles"] < 2 * counts["whole frame"]
