import copy
import dataclasses
import json

import pytest
import torch

from evlatcorr.benchmark.accuracy import TRAIN_SPLITS, case_reference, make_cases, simulate_case, training_target
from evlatcorr.curve_reader import (
    NUM_FEATURES,
    WEIGHTS_NAME,
    CurveReader,
    FusedCurveReaderEnsemble,
    curve_features,
    load_curve_reader,
    save_curve_reader,
    train_curve_reader,
    without_overshoot,
)


def test_features_are_relative_to_the_valid_part():
    scores = torch.tensor([[4.0, 2.0, 0.0, 99.0]] * 3)
    valid = torch.tensor([True, True, True, False])
    moment = torch.tensor([0.5, 0.0, -0.5, 7.0])
    overshoot = torch.tensor([0.25, 0.0, 1.5, 9.0])
    x = curve_features(scores, moment, valid, overshoot)
    assert x.shape == (NUM_FEATURES, 4)
    torch.testing.assert_close(x[0], torch.tensor([0.5, 0.0, -0.5, 0.0]))  # (s - median) / range, 0 past
    torch.testing.assert_close(x[3], torch.tensor([0.5, 0.0, -0.5, 0.0]))
    torch.testing.assert_close(x[4], torch.tensor([0.25, 0.0, 1.5, 0.0]))  # the overshoot as it is, 0 past
    torch.testing.assert_close(x[5], valid.float())
    # the same curves at another level and scale read the same
    torch.testing.assert_close(curve_features(10.0 + 3.0 * scores, moment, valid, overshoot), x)


def test_features_with_fewer_than_two_valid_candidates_are_zero():
    valid = torch.tensor([True, False, False, False, False])
    x = curve_features(torch.rand(3, 5), torch.zeros(5), valid, torch.zeros(5))
    assert torch.equal(x[:3], torch.zeros(3, 5))


def test_features_of_several_frames_at_once_equal_each_frames():
    g = torch.Generator().manual_seed(8)
    scores, moment, overshoot = torch.rand(4, 3, 9, generator=g), torch.randn(4, 9, generator=g), torch.rand(4, 9)
    valid = torch.ones(4, 9, dtype=torch.bool)
    valid[1, 5:] = False  # events that stop early
    valid[2, 1:] = False  # one valid candidate: no usable curve
    valid[3] = False  # nothing scored
    together = curve_features(scores, moment, valid, overshoot)
    assert together.shape == (4, NUM_FEATURES, 9)
    for n in range(4):
        torch.testing.assert_close(together[n], curve_features(scores[n], moment[n], valid[n], overshoot[n]),
                                   rtol=0, atol=0)


def test_features_refuse_mismatched_shapes():
    with pytest.raises(ValueError, match="scores must be"):
        curve_features(torch.rand(3, 5), torch.zeros(4), torch.ones(5, dtype=torch.bool), torch.zeros(5))
    with pytest.raises(ValueError, match="scores must be"):
        curve_features(torch.rand(2, 3, 5), torch.zeros(5), torch.ones(5, dtype=torch.bool), torch.zeros(5))
    with pytest.raises(ValueError, match="scores must be"):
        curve_features(torch.rand(3, 5), torch.zeros(5), torch.ones(5, dtype=torch.bool), torch.zeros(4))


def test_reader_never_picks_a_candidate_that_could_not_be_scored():
    valid = torch.zeros(1, 21, dtype=torch.bool)
    valid[0, :5] = True
    logits = CurveReader()(torch.randn(1, NUM_FEATURES, 21), valid)
    assert int(logits.argmax()) < 5


def test_fused_ensemble_is_the_ensemble():
    # the shipped weights in float64 (as on a GPU), on frames with candidates past the last event
    ensemble = copy.deepcopy(load_curve_reader()).double()  # the loaded one is cached: a copy to convert
    fused = FusedCurveReaderEnsemble(ensemble)
    g = torch.Generator().manual_seed(0)
    curves = torch.randn(4, NUM_FEATURES, 101, generator=g, dtype=torch.float64)
    valid = torch.ones(4, 101, dtype=torch.bool)
    valid[1, 60:] = False
    valid[2, 2:] = False
    out = fused(curves, valid)
    torch.testing.assert_close(out, ensemble(curves, valid), rtol=0, atol=1e-9)
    assert torch.equal(out.argmax(1), ensemble(curves, valid).argmax(1))
    assert fused.num_members == len(ensemble.members)
    # four convolutions in all, whatever the number of members
    assert sum(isinstance(m, torch.nn.Conv1d) for m in fused.modules()) == 4
    # float32 on a CPU, as the search runs it
    ensemble32 = load_curve_reader()
    with torch.no_grad():
        out32 = FusedCurveReaderEnsemble(ensemble32)(curves.float(), valid)
        reference32 = ensemble32(curves.float(), valid)
    torch.testing.assert_close(out32, reference32, rtol=1e-5, atol=1e-4)  # masked ones are about -1e4
    assert torch.equal(out32.argmax(1), reference32.argmax(1))


def test_fused_ensemble_refuses_anything_but_an_ensemble():
    with pytest.raises(ValueError, match="takes a CurveReaderEnsemble"):
        FusedCurveReaderEnsemble(CurveReader())


def _planted(n, generator):
    """Curves whose target is the minimum of the first score; the others are noise."""
    k = 41
    latencies = torch.arange(k, dtype=torch.float64) * 200.0
    where = torch.randint(5, k - 5, (n,), generator=generator)
    grid = torch.arange(k)
    scores = torch.rand(n, 3, k, generator=generator, dtype=torch.float64)
    scores[:, 0] = ((grid[None] - where[:, None]).abs() / k).double()
    valid = torch.ones(k, dtype=torch.bool)
    curves = torch.stack([curve_features(s, torch.zeros(k), valid, torch.zeros(k)) for s in scores])
    return curves, valid.expand(n, k).clone(), latencies, latencies[where]


def test_training_learns_a_planted_rule():
    g = torch.Generator().manual_seed(0)
    curves, valid, latencies, targets = _planted(64, g)
    ensemble = train_curve_reader(curves, valid, latencies, targets, members=2, epochs=150)
    test_curves, test_valid, _, test_targets = _planted(32, g)
    with torch.no_grad():
        picked = latencies[ensemble(test_curves, test_valid).argmax(1)]
    assert (picked - test_targets).abs().le(200.0).float().mean() >= 0.9


def test_save_and_load_round_trip(tmp_path):
    g = torch.Generator().manual_seed(1)
    curves, valid, latencies, targets = _planted(8, g)
    ensemble = train_curve_reader(curves, valid, latencies, targets, members=2, epochs=2)
    path = tmp_path / "reader.safetensors"
    save_curve_reader(ensemble, path, {"frames": 8})
    loaded = load_curve_reader(str(path))
    assert len(loaded.members) == 2 and path.with_suffix(".json").exists()
    with torch.no_grad():
        torch.testing.assert_close(loaded(curves, valid), ensemble(curves, valid))


def test_a_reader_without_the_overshoot_trains_saves_and_loads_with_its_inputs(tmp_path):
    g = torch.Generator().manual_seed(2)
    curves, valid, latencies, targets = _planted(8, g)
    curves[:, NUM_FEATURES - 2] = 7.0  # the overshoot's row: gone from what the reader reads
    fewer = without_overshoot(curves)
    assert fewer.shape == (8, NUM_FEATURES - 1, curves.shape[-1])
    assert not bool((fewer == 7.0).any()) and torch.equal(fewer[:, -1], curves[:, -1])  # the mask stays last
    ensemble = train_curve_reader(fewer, valid, latencies, targets, members=2, epochs=2)
    path = tmp_path / "reader5.safetensors"
    save_curve_reader(ensemble, path)
    loaded = load_curve_reader(str(path))
    assert loaded.members[0].net[0].in_channels == NUM_FEATURES - 1
    with torch.no_grad():
        torch.testing.assert_close(loaded(fewer, valid), ensemble(fewer, valid))
    with pytest.raises(ValueError, match="curves must be"):
        without_overshoot(fewer)


def test_a_wider_deeper_reader_trains_saves_and_loads_with_its_shape(tmp_path):
    g = torch.Generator().manual_seed(3)
    curves, valid, latencies, targets = _planted(8, g)
    ensemble = train_curve_reader(curves, valid, latencies, targets, members=2, epochs=2, channels=8, layers=5)
    reader = ensemble.members[0]
    convs = [m for m in reader.net if isinstance(m, torch.nn.Conv1d)]
    assert [c.dilation[0] for c in convs] == [1, 2, 4, 8, 16, 1] and convs[0].out_channels == 8
    # 5-tap layers dilated 1..16 see 62 candidates either side (the shipped three, 14): an impulse at the first
    # candidate moves outputs past the 14th and none past the 62nd
    impulse = torch.zeros(1, NUM_FEATURES, 101)
    impulse[0, 0, 0] = 1.0
    with torch.no_grad():
        moved = (reader.net(impulse) - reader.net(torch.zeros_like(impulse)))[0, 0]
    assert float(moved[15:63].abs().max()) > 0 and bool((moved[63:] == 0).all())
    path = tmp_path / "wide.safetensors"
    save_curve_reader(ensemble, path)
    load_curve_reader.cache_clear()
    loaded = load_curve_reader(str(path))
    with torch.no_grad():
        torch.testing.assert_close(loaded(curves, valid), ensemble(curves, valid))
    with pytest.raises(ValueError, match="at least one layer"):
        CurveReader(layers=0)


def test_shipped_weights_load_strictly():
    ensemble = load_curve_reader()
    assert len(ensemble.members) == 5 and not ensemble.training


def test_training_splits_are_disjoint_from_the_suite_and_have_targets():
    assert all(c.latency_model == "constant" for s in TRAIN_SPLITS[:-1] for c in make_cases(s, num=6))
    photo = make_cases("train_photo", num=6)
    assert all(c.latency_model == "intensity" for c in photo)
    seeds = {c.seed for s in ("dev", "test") for c in make_cases(s)}
    train = [c for s in TRAIN_SPLITS for c in make_cases(s)]
    assert not seeds & {c.seed for c in train} and len({c.seed for c in train}) == len(train) == 2000
    scenes = {c.scene_seed for s in ("dev", "test") for c in make_cases(s)} - {None}
    assert not scenes & {c.scene_seed for c in train}
    # the target: the true latency of a constant case, the best constant shift under the photoreceptor model
    constant = make_cases("train", num=1)[0]
    assert training_target(constant, simulate_case(constant)[0]) == constant.latency_us
    small_photo = dataclasses.replace(photo[0], size=(32, 32))
    delayed = simulate_case(small_photo)[0]
    assert training_target(small_photo, delayed) == case_reference(small_photo)["best_shift_us"]
    delay = dataclasses.replace(make_cases("dev")[0], size=(32, 32))
    with pytest.raises(ValueError, match="no training target"):
        training_target(delay, simulate_case(delay)[0])


def test_shipped_weights_are_small_and_say_how_they_were_made():
    from evlatcorr.locations import checkpoint_dirs

    weights = checkpoint_dirs()[-2] / f"{WEIGHTS_NAME}.safetensors"  # the repository's checkpoints/
    assert weights.stat().st_size <= 100_000
    provenance = json.loads(weights.with_suffix(".json").read_text())
    assert provenance["cases"] == list(TRAIN_SPLITS) and provenance["frames"] == 2000


def test_training_and_loading_refuse_bad_input(tmp_path):
    curves, valid, latencies, targets = _planted(4, torch.Generator().manual_seed(2))
    with pytest.raises(ValueError, match="need curves"):
        train_curve_reader(curves, valid[:, :-1], latencies, targets)
    with pytest.raises(ValueError, match="need curves"):
        train_curve_reader(curves, valid, latencies, targets[:-1])
    with pytest.raises(FileNotFoundError, match="no curve reader weights"):
        load_curve_reader(str(tmp_path / "missing.safetensors"))
