from __future__ import annotations

import math

import lightning as L
import pytest
import torch
from lightning.pytorch.trainer.connectors.data_connector import warning_cache

from evlatcorr import EventLatencyCorrector
from evlatcorr.adapters.edi import EDIAdapter
from evlatcorr.adapters.refid import refid_inputs
from evlatcorr.benchmark import (
    CONST,
    GT,
    NO_CORR,
    BenchmarkModule,
    BenchmarkScene,
    Method,
    SceneDataModule,
    diff_percent,
    format_table,
    pair_with_latency,
)
from evlatcorr.simulate import simulate


def scene(seed: int) -> BenchmarkScene:
    seq = simulate("coffee", num_frames=2, height=48, width=64, latency="constant", latency_us=4000.0, seed=seed,
                   exposure_us=10000.0, frame_interval_us=12000.0)
    return BenchmarkScene(f"coffee{seed}", seq.frames("ideal"), seq.frames("delayed"), seq.pairs("ideal"),
                          seq.pairs("delayed"), seq.true_latency)


def test_diff_percent_definition():
    assert diff_percent(28.0, 26.0, 27.5) == pytest.approx((27.5 - 26.0) / 28.0 * 100)
    assert math.isnan(diff_percent(float("nan"), 1.0, 2.0))


def test_edi_rows_on_a_lightning_test_loop(recwarn):
    warning_cache.clear()  # Lightning says a hook warning once per process
    methods = [Method("EDI deblurring", EDIAdapter(num_bins=100), "deblur"),
               Method("EDI interpolation", EDIAdapter("interpolation", num_bins=100), "interpolation")]
    module = BenchmarkModule(methods, {CONST: EventLatencyCorrector(num_bins=100)})
    trainer = L.Trainer(accelerator="cpu", devices=1, logger=False, enable_progress_bar=False,
                        enable_model_summary=False)
    trainer.test(module, SceneDataModule(lambda i: scene(i), 2))
    results = module.results()
    rows = {(r["method"], r["input"]): r for r in results["table"]}
    assert len(results["table"]) == 6
    deblur = "EDI deblurring"
    assert rows[(deblur, GT)]["psnr"] > rows[(deblur, NO_CORR)]["psnr"] + 2.0
    assert rows[(deblur, CONST)]["psnr"] > rows[(deblur, NO_CORR)]["psnr"]
    assert results["latency_error"][CONST]["mae_us"] < 4000.0  # better than not correcting
    table = format_table(results)
    assert "Diff (%) const." in table and "| EDI interpolation | GT input |" in table
    # the scenes move by Lightning's own batch transfer, with no overridden hook to warn about
    assert not [w for w in recwarn if "transfer_batch_to_device" in str(w.message)]


class _FrameRecorder(torch.nn.Module):
    """A stand-in network that restores nothing: it returns the blurry frame it was given, and keeps it."""

    def forward(self, batch):
        self.seen = batch.blurry
        return batch.with_outputs(output=batch.blurry)


def test_rows_are_scored_as_the_file_encoded_its_frames():
    # a scene read with frame_gamma 2.2 holds linear frames: a network reads them encoded back, EDI reads them
    # linear, and both are scored against the sharp frame encoded back
    from evlatcorr.benchmark.loop import _run

    frames = scene(0).frames_ideal
    network, edi = Method("net", _FrameRecorder(), "deblur"), Method("EDI", EDIAdapter(num_bins=50), "deblur")
    assert (network.linear, edi.linear) == (False, True)
    restored, target = _run(network, frames, 2.2)
    torch.testing.assert_close(network.model.seen, frames.blurry.clamp(0, 1) ** (1 / 2.2))
    torch.testing.assert_close(restored, frames.blurry.clamp(0, 1) ** (1 / 2.2))
    torch.testing.assert_close(target, frames.sharp.clamp(0, 1) ** (1 / 2.2))
    plain, _ = _run(edi, frames)
    encoded, target = _run(edi, frames, 2.2)
    torch.testing.assert_close(encoded, plain ** (1 / 2.2))
    torch.testing.assert_close(target, frames.sharp.clamp(0, 1) ** (1 / 2.2))
    restored, target = _run(network, frames)  # linear files: as before
    assert torch.equal(restored, frames.blurry.clamp(0, 1)) and torch.equal(target, frames.sharp)


def test_pairs_corrected_with_the_true_latency_give_refid_the_ideal_input():
    # REFID's voxel grid starts half a sharp-frame interval before the exposure, where the ideal pairs
    # have no events: corrected events moved there would give it an input the ideal events never do
    seq = simulate("coffee", num_frames=2, height=16, width=20, latency="constant", latency_us=4000.0, seed=0,
                   exposure_us=10000.0, frame_interval_us=12000.0)
    ideal, delayed = seq.pairs("ideal"), seq.pairs("delayed")
    latency = torch.full((1,), 4000.0, dtype=torch.float64)
    window = pair_with_latency(delayed, latency, latency, delayed.exposure_start)
    assert bool((window.corrected.t >= delayed.exposure_start[0]).all())
    x_ideal, event_ideal = refid_inputs(ideal, m=4, n=1)
    x_window, event_window = refid_inputs(window, m=4, n=1)
    torch.testing.assert_close(event_window, event_ideal, atol=1e-4, rtol=0)
    torch.testing.assert_close(x_window, x_ideal, atol=1e-4, rtol=0)
    _, event_uncut = refid_inputs(pair_with_latency(delayed, latency, latency), m=4, n=1)
    assert not torch.allclose(event_uncut, event_ideal, atol=1e-4)


def test_pair_with_latency_rejects_a_window_start_of_the_wrong_shape():
    delayed = scene(0).pairs_delayed
    latency = torch.zeros(1, dtype=torch.float64)
    with pytest.raises(ValueError, match="start"):
        pair_with_latency(delayed, latency, latency, torch.zeros(3))
