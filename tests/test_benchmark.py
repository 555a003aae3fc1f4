from __future__ import annotations

import math

import lightning as L
import pytest

from evlatcorr import EventLatencyCorrector
from evlatcorr.adapters.edi import EDIAdapter
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


def test_edi_rows_on_a_lightning_test_loop():
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
