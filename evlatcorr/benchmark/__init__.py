"""The paper's Table 1 and the latency accuracy suite: scenes, the Lightning test loop, metrics and tables.

- :mod:`evlatcorr.benchmark.loop`: :class:`BenchmarkModule` (every method on every input of each scene) and
  :class:`SceneDataModule`;
- :mod:`evlatcorr.benchmark.metrics`: PSNR/SSIM/LPIPS as a ``MetricCollection``, :class:`LatencyError`;
- :mod:`evlatcorr.benchmark.table`: the markdown table with the "Diff (%)" rows;
- :mod:`evlatcorr.benchmark.table1`: the command line behind ``python benchmarks/run.py``.
"""

from evlatcorr.benchmark.loop import (
    CONST,
    GT,
    INPUTS,
    NO_CORR,
    SPATIAL,
    BenchmarkModule,
    BenchmarkScene,
    Method,
    SceneDataModule,
    pair_with_latency,
)
from evlatcorr.benchmark.metrics import LPIPS, ImageQuality, LatencyError, load_lpips_network
from evlatcorr.benchmark.table import diff_percent, format_table

__all__ = [
    "CONST",
    "GT",
    "INPUTS",
    "NO_CORR",
    "SPATIAL",
    "BenchmarkModule",
    "BenchmarkScene",
    "ImageQuality",
    "LPIPS",
    "LatencyError",
    "Method",
    "SceneDataModule",
    "diff_percent",
    "format_table",
    "load_lpips_network",
    "pair_with_latency",
]
