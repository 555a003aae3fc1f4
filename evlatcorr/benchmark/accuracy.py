"""A seeded accuracy suite for latency estimators on simulated scenes (``benchmarks/accuracy.py``).

Two splits of one-frame cases, each drawn from its own fixed seed:

- ``"dev"``: :data:`~evlatcorr.simulate.PHOTOGRAPHS_TRAIN` photographs and procedural scenes with
  one set of seeds; tune on it.
- ``"dev_wide"``: 120 more cases of the dev split's distribution (its photographs, seeds of their own): tune on
  it with ``"dev"`` where 40 cases cannot tell two estimators apart (their medians move by about 100 µs
  between draws, and one case decides a worst figure).
- ``"test"``: :data:`~evlatcorr.simulate.PHOTOGRAPHS_TEST` photographs and procedural scenes with
  disjoint seeds; report on it.

Each factor (scene, dark background, brightness, motion kind, speed, direction, latency model,
latency, each noise model, threshold) is drawn from its own generator stream, categorical factors
as a shuffled balanced list, so every split covers every procedural kind, motion kind, latency
model and noise model, and dark scenes. A case is a 20 ms exposure of a ``(96, 128)`` sensor
whose events stop 15 ms after the exposure's end.

:func:`evaluate_case` scores an estimator (delayed :class:`~evlatcorr.frames.EventFrames` in, a
latency map :math:`(B, 1, H, W)` µs out): the latency error, and EDI PSNR against the sharp
mid-exposure frame with ideal events, with the delayed events uncorrected and corrected by the
estimated map; the recovery ``(corr − uncorr) / (ideal − uncorr)``; for the photoreceptor model
(``"intensity"``) also the best constant shift's PSNR (an oracle) and the share of its gain the
estimator achieves; and the estimator on the case's ideal events, where 0 is right, with what correcting them by
its answer does to their EDI PSNR.

Example:
    >>> cases = make_cases("test")
    >>> len(cases) >= 48, cases[0].split
    (True, 'test')
"""

from __future__ import annotations

import csv
import dataclasses
import importlib
import importlib.util
import json
import math
import re
import statistics
import time
import warnings
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from evlatcorr.benchmark import compare
from evlatcorr.benchmark.compare import NO_GAP_DB, edi_psnr, psnr
from evlatcorr.edi import edi_deblur, event_grid
from evlatcorr.frames import EventFrames
from evlatcorr.scenes import PROCEDURAL_SCENES, procedural_scene
from evlatcorr.simulate import PHOTOGRAPHS_TEST, PHOTOGRAPHS_TRAIN, ObjectSpec, SimulatedSequence, simulate

__all__ = [
    "SPLITS",
    "LATENCY_MODELS",
    "MOTION_KINDS",
    "DEFAULT_SIZE",
    "Case",
    "make_cases",
    "simulate_case",
    "case_reference",
    "training_target",
    "evaluate_case",
    "corrector_estimator",
    "load_estimator",
    "run_suite",
    "summarize",
    "warning_kinds",
    "to_markdown",
    "write_results",
]

Estimator = Callable[[EventFrames], "Tensor | EventFrames"]  # a latency map, or frames holding one

SPLITS = ("dev", "dev_wide", "test")
LATENCY_MODELS = ("constant", "intensity_delay", "intensity")
MOTION_KINDS = ("translation", "random", "rotation", "zoom", "objects")
DEFAULT_SIZE = (96, 128)
EXPOSURE_US = 20_000.0
AFTER_US = 15_000.0  # the events stop this long after the exposure's end
BEST_SHIFTS_US = tuple(250.0 * i for i in range(61))  # the oracle's constant latencies, 0..15000 µs
DARK_BRIGHTNESS = 0.1
DARK_PHOTOGRAPHS = ("hubble_deep_field", "moon")  # photographs with large uniform dark regions
SCENE_FACTOR = 3  # procedural scenes are this many times the sensor's size

# the learned curve reader's training cases (evlatcorr.curve_reader): the dev split's photographs, seeds disjoint
# from dev and test; constant latency in four batches of 200, 300, 400 and 900 cases, then 200 photoreceptor cases
TRAIN_SPLITS = ("train", "train1", "train2", "train3", "train_photo")
_NUM_CASES = {"dev": 40, "dev_wide": 120, "test": 48, "train": 200, "train1": 300, "train2": 400, "train3": 900,
              "train_photo": 200}
_PHOTOGRAPHS = {"dev": PHOTOGRAPHS_TRAIN, "dev_wide": PHOTOGRAPHS_TRAIN, "test": PHOTOGRAPHS_TEST,
                **{s: PHOTOGRAPHS_TRAIN for s in TRAIN_SPLITS}}
# case draws: generator seed 1000 * split seed + factor index
_SPLIT_SEED = {"dev": 1, "test": 2, "train": 3, "train1": 4, "train2": 5, "train3": 6, "train_photo": 7, "dev_wide": 11}
# procedural scenes and sprites: disjoint seed ranges
_SCENE_SEED = {"dev": 100_000, "test": 200_000, "train": 300_000, "train1": 400_000, "train2": 500_000,
               "train3": 600_000, "train_photo": 700_000, "dev_wide": 1_100_000}
_SIM_SEED = {"dev": 10_000, "test": 20_000, "train": 30_000, "train1": 40_000, "train2": 50_000, "train3": 60_000,
             "train_photo": 70_000, "dev_wide": 110_000}
_MOTION_WEIGHTS = (0.3, 0.15, 0.2, 0.15, 0.2)
_LATENCY_WEIGHTS = (0.5, 0.25, 0.25)
_TRAIN_LATENCY_WEIGHTS = (1.0, 0.0, 0.0)
_SPLIT_LATENCY_WEIGHTS = {"train_photo": (0.0, 0.0, 1.0)}
_MOTION_TAGS = {"translation": "tr", "random": "rnd", "rotation": "rot", "zoom": "zoom", "objects": "obj"}
_LATENCY_TAGS = {"constant": "const", "intensity_delay": "delay", "intensity": "photo"}


@dataclass(frozen=True)
class Case:
    """One simulated frame of the suite and everything needed to simulate it again.

    Attributes:
        name: readable unique name, e.g. ``test-07-camera-b0.05-rot1.3-const4200`` (procedural
            scenes as ``proc-<kind>``).
        split: one of :data:`SPLITS` (or :data:`TRAIN_SPLITS`).
        scene: a photograph name, or a procedural kind (:data:`~evlatcorr.scenes.PROCEDURAL_SCENES`)
            when ``scene_seed`` is set (``"text"`` is both).
        scene_seed: seed of a procedural scene; None for a photograph.
        dark_background: a procedural scene drawn with ``dark=True`` (large black regions).
        brightness: scene intensity scale (0.03-1).
        motion: one of :data:`MOTION_KINDS`: ``"translation"`` (constant, ``direction_deg``),
            ``"random"`` (the simulator's smooth random motion), ``"rotation"``, ``"zoom"``, or
            ``"objects"`` (two sprites over a static background).
        speed_px_per_ms: image speed (the largest, or at the view's corners), px/ms.
        direction_deg: direction of a translation or of the first object, degrees.
        latency_model: one of :data:`LATENCY_MODELS`.
        latency_us: the constant latency, µs (0 for the other models).
        latency_range_us: ``(bright, dim)`` time constants of the intensity models, µs.
        noise_rate_hz: shot noise, events per pixel per second.
        leak_rate_hz: leak events per pixel per second.
        threshold_sigma: relative per-pixel threshold mismatch.
        refractory_us: per-pixel dead time, µs.
        threshold: contrast threshold (log units); the true one is given to the estimators and EDI.
        objects: ``(scene, seed)`` of each object's sprite when ``motion == "objects"`` (seed None: a
            photograph).
        seed: simulation seed (motion, noise, objects' placement).
        size: sensor ``(H, W)``.
        exposure_us: exposure time, µs.
        after_us: how long the events run on after the exposure's end, µs.
    """

    name: str
    split: str
    scene: str
    scene_seed: int | None
    dark_background: bool
    brightness: float
    motion: str
    speed_px_per_ms: float
    direction_deg: float
    latency_model: str
    latency_us: float
    latency_range_us: tuple[float, float]
    noise_rate_hz: float
    leak_rate_hz: float
    threshold_sigma: float
    refractory_us: float
    threshold: float
    objects: tuple[tuple[str, int | None], ...] = ()
    seed: int = 0
    size: tuple[int, int] = DEFAULT_SIZE
    exposure_us: float = EXPOSURE_US
    after_us: float = AFTER_US

    @property
    def procedural(self) -> bool:
        """The scene is procedural (not a photograph)."""
        return self.scene_seed is not None

    @property
    def dark(self) -> bool:
        """A dim scene: ``brightness <= 0.1``."""
        return self.brightness <= DARK_BRIGHTNESS

    @property
    def dark_regions(self) -> bool:
        """The scene has large uniform dark regions (a dark procedural background or a dark photograph)."""
        return self.dark_background or (not self.procedural and self.scene in DARK_PHOTOGRAPHS)

    @property
    def noise_models(self) -> tuple[str, ...]:
        """The noise models switched on: ``"shot"``, ``"leak"``, ``"mismatch"``, ``"refractory"``."""
        on = (self.noise_rate_hz > 0, self.leak_rate_hz > 0, self.threshold_sigma > 0, self.refractory_us > 0)
        return tuple(n for n, o in zip(("shot", "leak", "mismatch", "refractory"), on) if o)

    def to_dict(self) -> dict[str, Any]:
        """The fields as JSON-serialisable values (tuples as lists)."""
        return json.loads(json.dumps(dataclasses.asdict(self)))


# --- cases -----------------------------------------------------------------------------------------------------------
def _generator(split: str, factor: int) -> torch.Generator:
    return torch.Generator().manual_seed(1000 * _SPLIT_SEED[split] + factor)


def _balanced(choices: Sequence[Any], weights: Sequence[float], n: int, g: torch.Generator) -> list[Any]:
    """``n`` draws in proportion to ``weights`` (largest remainders), shuffled: a weight >= 1/n is always drawn."""
    total = sum(weights)
    exact = [w / total * n for w in weights]
    counts = [math.floor(e) for e in exact]
    for i in sorted(range(len(exact)), key=lambda i: counts[i] - exact[i])[: n - sum(counts)]:
        counts[i] += 1
    items = [c for c, k in zip(choices, counts) for _ in range(k)]
    return [items[i] for i in torch.randperm(n, generator=g).tolist()]


def _stratified(n: int, g: torch.Generator) -> list[float]:
    """``n`` numbers in [0, 1), one in each of ``n`` equal strata, shuffled (Latin hypercube in 1-D)."""
    perm = torch.randperm(n, generator=g).double()
    return ((perm + torch.rand(n, generator=g, dtype=torch.float64)) / n).tolist()


def _log_uniform(u: float, lo: float, hi: float) -> float:
    return math.exp(math.log(lo) + u * (math.log(hi) - math.log(lo)))


def make_cases(split: str, num: int | None = None, size: tuple[int, int] = DEFAULT_SIZE) -> list[Case]:
    """The suite's cases of one split, the same on every machine.

    Args:
        split: ``"dev"`` (40 cases), ``"dev_wide"`` (120), ``"test"`` (48 cases), or one of :data:`TRAIN_SPLITS`
            (constant latency, and the photoreceptor model in ``"train_photo"``: what the learned curve reader is
            trained on; never reported).
        num: keep only the first ``num`` cases (a random subset that may miss some factors).
        size: sensor ``(H, W)``.

    Returns:
        the cases, in a fixed order.

    Example:
        >>> len(make_cases("dev")), len(make_cases("test"))
        (40, 48)
        >>> [c.name for c in make_cases("dev", num=2)]
        ['dev-00-cell-b0.06-rot0.2-delay', 'dev-01-retina-b0.66-rot1.1-photo']
    """
    if split not in SPLITS + TRAIN_SPLITS:
        raise ValueError(f"split must be one of {SPLITS + TRAIN_SPLITS}, got {split!r}")
    if num is not None and (not isinstance(num, int) or num < 0):
        raise ValueError(f"num must be a non-negative integer or None, got {num!r}")
    if len(size) != 2 or not all(isinstance(s, int) and s >= 16 for s in size):
        raise ValueError(f"size must be (H, W) integers >= 16, got {size}")
    n = _NUM_CASES[split]
    pool = tuple((p, False) for p in _PHOTOGRAPHS[split]) + tuple((k, True) for k in PROCEDURAL_SCENES)
    scenes = _balanced(pool, [1.0] * len(pool), n, _generator(split, 0))
    dark_bg = [u < 0.4 for u in _stratified(n, _generator(split, 1))]
    dark_bg = [d and procedural for d, (_, procedural) in zip(dark_bg, scenes)]
    if not any(d and s == ("shapes", True) for d, s in zip(dark_bg, scenes)):  # shapes on black, always
        dark_bg[scenes.index(("shapes", True))] = True
    brightness = [_log_uniform(u, 0.03, 1.0) for u in _stratified(n, _generator(split, 2))]
    motions = _balanced(MOTION_KINDS, _MOTION_WEIGHTS, n, _generator(split, 3))
    speeds = [_log_uniform(u, 0.2, 4.0) for u in _stratified(n, _generator(split, 4))]
    directions = (torch.rand(n, generator=_generator(split, 5), dtype=torch.float64) * 360).tolist()
    weights = _SPLIT_LATENCY_WEIGHTS.get(split, _TRAIN_LATENCY_WEIGHTS if split in TRAIN_SPLITS else _LATENCY_WEIGHTS)
    models = _balanced(LATENCY_MODELS, weights, n, _generator(split, 6))
    latencies = [200.0 + u * 11_800.0 for u in _stratified(n, _generator(split, 7))]
    g = _generator(split, 8)
    ranges = [(200.0 + 800.0 * float(a), 4000.0 + 8000.0 * float(b))
              for a, b in torch.rand(n, 2, generator=g, dtype=torch.float64).tolist()]
    noise_on = [_balanced((True, False), (1.0, 1.0), n, _generator(split, 9 + k)) for k in range(4)]
    noise_u = torch.rand(4, n, generator=_generator(split, 13), dtype=torch.float64).tolist()
    thresholds = [0.15 + 0.15 * u for u in _stratified(n, _generator(split, 14))]
    g_obj = _generator(split, 15)
    cases = []
    for i in range(n):
        scene_seed = _SCENE_SEED[split] + 10 * i
        objects: tuple[tuple[str, int | None], ...] = ()
        if motions[i] == "objects":
            picks = torch.randint(0, len(pool), (2,), generator=g_obj).tolist()
            objects = tuple((pool[k][0], scene_seed + 1 + j if pool[k][1] else None) for j, k in enumerate(picks))
        model = models[i]
        fields = dict(
            split=split, scene=scenes[i][0], scene_seed=scene_seed if scenes[i][1] else None,
            dark_background=dark_bg[i],
            brightness=round(brightness[i], 3), motion=motions[i], speed_px_per_ms=round(speeds[i], 2),
            direction_deg=round(directions[i], 1), latency_model=model,
            latency_us=float(round(latencies[i], -1)) if model == "constant" else 0.0,
            latency_range_us=(float(round(ranges[i][0], -1)), float(round(ranges[i][1], -1))),
            noise_rate_hz=round(_log_uniform(noise_u[0][i], 0.5, 10.0), 2) if noise_on[0][i] else 0.0,
            leak_rate_hz=round(_log_uniform(noise_u[1][i], 0.1, 2.0), 2) if noise_on[1][i] else 0.0,
            threshold_sigma=round(0.03 + 0.12 * noise_u[2][i], 3) if noise_on[2][i] else 0.0,
            refractory_us=float(round(_log_uniform(noise_u[3][i], 50.0, 1000.0), -1)) if noise_on[3][i] else 0.0,
            threshold=round(thresholds[i], 3), objects=objects, seed=_SIM_SEED[split] + i, size=tuple(size),
        )
        cases.append(Case(name=_case_name(i, fields), **fields))
    return cases if num is None else cases[:num]


def _case_name(i: int, f: Mapping[str, Any]) -> str:
    scene = ("proc-" if f["scene_seed"] is not None else "") + f["scene"] + ("-dark" if f["dark_background"] else "")
    latency = {"constant": f"const{f['latency_us']:.0f}", "intensity_delay": "delay",
               "intensity": "photo"}[f["latency_model"]]
    return (f"{f['split']}-{i:02d}-{scene}-b{f['brightness']:.2f}-{_MOTION_TAGS[f['motion']]}"
            f"{f['speed_px_per_ms']:.1f}-{latency}")


# --- simulation ------------------------------------------------------------------------------------------------------
def _scene_image(scene: str, seed: int | None, dark: bool, size: tuple[int, int]) -> str | Tensor:
    if seed is None:
        return scene
    return procedural_scene(scene, SCENE_FACTOR * size[0], SCENE_FACTOR * size[1], seed, dark=dark)


def _object_specs(case: Case) -> list[ObjectSpec]:
    """Two objects crossing the view near its centre at mid-exposure (placement drawn from ``case.seed``)."""
    g = torch.Generator().manual_seed(case.seed)
    u = torch.rand(len(case.objects), 6, generator=g, dtype=torch.float64).tolist()
    h, w = case.size
    t_mid = case.after_us + case.exposure_us / 2  # the simulation's margin is after_us
    specs = []
    for j, ((sprite, seed), v) in enumerate(zip(case.objects, u)):
        oh = max(8, round(h * (0.35 + 0.2 * v[0])))
        ow = max(8, min(round(0.6 * w), round(oh * (0.8 + 0.6 * v[1]))))
        angle = math.radians(case.direction_deg) + (0.0 if j == 0 else math.pi * (0.5 + v[2]))
        speed = case.speed_px_per_ms * (1.0 if j == 0 else 0.5 + 0.5 * v[3])
        x, y = (w - 1) / 2 + 0.4 * w * (v[4] - 0.5), (h - 1) / 2 + 0.4 * h * (v[5] - 0.5)
        specs.append(ObjectSpec(sprite if seed is None else (sprite, seed), (oh, ow), (x, y),
                                (speed * math.cos(angle), speed * math.sin(angle)),
                                shape="disc" if j % 2 == 0 else "rect", time_us=t_mid))
    return specs


def simulate_case(case: Case, num_frames: int = 1, before_us: float = 0.0
                  ) -> tuple[EventFrames, EventFrames, SimulatedSequence]:
    """Simulate a case.

    Args:
        case: the case.
        num_frames: frames of the case's scene and motion, back to back (each exposure starts where the previous
            one ends): a sequence of one recording, for :mod:`evlatcorr.temporal`. Its first frame is not the
            one-frame case's: the simulator draws noise and random motion over the whole sequence.
        before_us: the frames also keep the events of this long before each exposure (as a recording's stream
            has them; the simulation is the same), at most ``case.after_us``.

    Returns:
        ``(delayed, ideal, seq)``: :class:`EventFrames` of ``num_frames`` samples of the delayed and the ideal
        events of ``[exposure_start − before_us, exposure_end + case.after_us)`` (``sharp`` and
        ``meta["true_latency"]`` :math:`(F, 1, H, W)` filled) and the :class:`SimulatedSequence`.
    """
    if not isinstance(case, Case):
        raise ValueError(f"case must be a Case, got {type(case).__name__}")
    if isinstance(num_frames, bool) or not isinstance(num_frames, int) or num_frames < 1:
        raise ValueError(f"num_frames must be a whole number >= 1, got {num_frames!r}")
    if not (math.isfinite(before_us) and 0.0 <= before_us <= case.after_us):
        raise ValueError(f"before_us must be between 0 and the simulated margin {case.after_us} us, got {before_us}")
    kwargs: dict[str, Any] = dict(
        num_frames=num_frames, height=case.size[0], width=case.size[1], exposure_us=case.exposure_us,
        frame_interval_us=case.exposure_us, latency=case.latency_model, latency_us=case.latency_us,
        latency_range_us=tuple(case.latency_range_us), threshold=case.threshold,
        threshold_sigma=case.threshold_sigma, noise_rate_hz=case.noise_rate_hz, leak_rate_hz=case.leak_rate_hz,
        refractory_us=case.refractory_us, brightness=case.brightness, margin_us=case.after_us, seed=case.seed)
    if case.motion == "translation":
        angle = math.radians(case.direction_deg)
        kwargs["motion"] = (case.speed_px_per_ms * math.cos(angle), case.speed_px_per_ms * math.sin(angle))
    elif case.motion == "objects":
        kwargs["objects"] = _object_specs(case)
    else:
        kwargs.update(motion=case.motion, max_speed_px_per_ms=case.speed_px_per_ms)
    seq = simulate(_scene_image(case.scene, case.scene_seed, case.dark_background, case.size), **kwargs)
    return (seq.frames("delayed", before_us=before_us, after_us=case.after_us),
            seq.frames("ideal", before_us=before_us, after_us=case.after_us), seq)


# --- evaluation ------------------------------------------------------------------------------------------------------
def _gain_ratio(value: float, low: float, high: float) -> float:
    """``(value − low) / (high − low)``, NaN when ``high <= low + NO_GAP_DB``."""
    return compare.recovery(value, low, high, NO_GAP_DB)


def case_reference(case: Case, simulated: tuple[EventFrames, EventFrames, SimulatedSequence] | None = None
                   ) -> dict[str, Any]:
    """What does not depend on the estimator: EDI PSNR with ideal and uncorrected events, true latency stats,
    and for the ``"constant"`` and ``"intensity"`` models the best constant shift: the oracle latency whose EDI
    is closest to the sharp frame (a scan of :data:`BEST_SHIFTS_US` refined to 62.5 µs). For a constant
    latency it shows how far EDI's own optimum lies from the true latency.

    Returns:
        a dict with ``psnr_ideal``, ``psnr_uncorrected``, ``true_latency_us`` (mean), ``true_latency_min_us``,
        ``true_latency_max_us``, ``num_events``, ``best_shift_us`` and ``psnr_best_shift`` (NaN for
        ``"intensity_delay"``).
    """
    delayed, ideal, _ = simulated if simulated is not None else simulate_case(case)
    true = delayed.meta["true_latency"]
    ref: dict[str, Any] = dict(
        psnr_ideal=edi_psnr(ideal, case.threshold), psnr_uncorrected=edi_psnr(delayed, case.threshold),
        true_latency_us=float(true.mean()), true_latency_min_us=float(true.min()),
        true_latency_max_us=float(true.max()), num_events=len(delayed.events),
        best_shift_us=math.nan, psnr_best_shift=math.nan)
    if case.latency_model in ("constant", "intensity"):
        ref.update(_best_shift(delayed, case.threshold))
    return ref


def _best_shift(delayed: EventFrames, threshold: float) -> dict[str, float]:
    """The oracle: the constant latency whose EDI is closest to the sharp frame in PSNR.

    A scan of :data:`BEST_SHIFTS_US`, then two halvings of the step around the best (±125, ±62.5 µs).
    """
    grid = event_grid(delayed.events, delayed.exposure_start, delayed.exposure_end, 500, (0.0, max(BEST_SHIFTS_US)))

    def psnr_at(shift: float) -> float:
        return psnr(edi_deblur(delayed.blurry, delayed.events, delayed.exposure_start, delayed.exposure_end,
                                threshold=threshold, latency=shift, grid=grid), delayed.sharp)

    best = max((psnr_at(shift), shift) for shift in BEST_SHIFTS_US)
    step = BEST_SHIFTS_US[1] - BEST_SHIFTS_US[0]
    for _ in range(2):
        step /= 2
        around = [s for s in (best[1] - step, best[1] + step) if BEST_SHIFTS_US[0] <= s <= BEST_SHIFTS_US[-1]]
        best = max([best, *((psnr_at(s), s) for s in around)])
    return {"psnr_best_shift": best[0], "best_shift_us": best[1]}


def training_target(case: Case, delayed: EventFrames) -> float:
    """What the learned curve reader is trained to pick for a training case, µs: the true latency of a constant
    one, the best constant shift (:func:`case_reference`'s oracle) under the photoreceptor model, where no one
    latency is true.

    Raises:
        ValueError: for the ``"intensity_delay"`` model (a map, with no best shift computed).
    """
    if case.latency_model == "constant":
        return case.latency_us
    if case.latency_model == "intensity":
        return _best_shift(delayed, case.threshold)["best_shift_us"]
    raise ValueError(f"no training target for the {case.latency_model!r} latency model")


def _as_map(latency: Any, frames: EventFrames) -> Tensor:
    b, (h, w) = frames.batch_size, frames.sensor_size
    if isinstance(latency, EventFrames):
        latency = latency.latency
    if not isinstance(latency, Tensor):
        try:
            latency = torch.as_tensor(latency, dtype=torch.float64)
        except (TypeError, ValueError):
            raise ValueError(f"the estimator must return a latency map (B, 1, H, W) in µs, got "
                             f"{type(latency).__name__}") from None
    latency = latency.detach().to(frames.device, torch.float64)
    if latency.dim() in (0, 1) and latency.numel() in (1, b):
        latency = latency.reshape(-1, 1, 1, 1).expand(b, 1, h, w)
    if tuple(latency.shape) != (b, 1, h, w):
        raise ValueError(f"the estimator must return a latency map of shape {(b, 1, h, w)} in µs, got "
                         f"{tuple(latency.shape)}")
    if not bool(torch.isfinite(latency).all()):
        raise ValueError("the estimator returned NaN or infinite latencies")
    return latency


def evaluate_case(case: Case, estimate: Estimator, *,
                  simulated: tuple[EventFrames, EventFrames, SimulatedSequence] | None = None,
                  reference: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """Score one estimator on one case.

    Args:
        case: the case.
        estimate: takes the delayed :class:`EventFrames` (one frame; ``meta["threshold"]`` holds the
            case's true threshold) and returns its latency map :math:`(B, 1, H, W)` µs (a scalar,
            a :math:`(B,)` vector or an :class:`EventFrames` with ``latency`` are accepted too), e.g.
            ``lambda f: EventLatencyCorrector(threshold=case.threshold)(f).latency``.
        simulated: ``simulate_case(case)``, to reuse it across estimators.
        reference: ``case_reference(case, simulated)``, to reuse it across estimators.

    Returns:
        the case's fields, :func:`case_reference`'s values and ``est_latency_us`` (mean of the map),
        ``latency_error_us`` (constant: estimate − true; maps: mean |map − true| over pixels),
        ``latency_abs_error_us``, ``latency_bias_us`` (mean estimate − mean truth), ``psnr_corrected``,
        ``recovery`` (NaN when there is no gap), ``no_gap``, ``best_shift_share`` (the share of the best
        constant shift's PSNR gain; NaN for ``"intensity_delay"``), ``latency_spread_us`` (the learned reader's,
        when ``estimate`` returns the corrector's frames; else NaN), ``ideal_estimate_us`` (the estimator's
        latency on the case's ideal events, where 0 is right), ``ideal_psnr_change_db`` (their EDI PSNR corrected by
        it, minus as they are), ``time_s`` (the estimate's wall time) and
        ``warnings`` (messages raised by it) and ``error`` (empty; when the estimator raised, its exception as
        ``"Type: message"``, with NaN estimates and scores: one case's failure does not stop a suite).
    """
    simulated = simulated if simulated is not None else simulate_case(case)
    delayed = simulated[0]
    ref = dict(reference) if reference is not None else case_reference(case, simulated)
    frames = delayed.replace(meta={**delayed.meta, "threshold": case.threshold})
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        t0 = time.perf_counter()
        try:
            raw, error = estimate(frames), ""
        except Exception as exc:  # noqa: BLE001 - one case's failure is recorded, the suite goes on
            raw, error = None, f"{type(exc).__name__}: {exc}"
        elapsed = time.perf_counter() - t0
    scores = dict.fromkeys(_ESTIMATE_COLUMNS, math.nan) if error else _estimate_columns(case, delayed, ref, raw)
    return {
        **_case_columns(case), **ref, **scores, **_ideal_columns(case, estimate, simulated[1], ref["psnr_ideal"]),
        "no_gap": not ref["psnr_ideal"] > ref["psnr_uncorrected"] + NO_GAP_DB, "time_s": elapsed,
        "warnings": sorted({str(w.message) for w in caught}), "error": error,
    }


def _ideal_columns(case: Case, estimate: Estimator, ideal: EventFrames, psnr_ideal: float) -> dict[str, float]:
    """The estimator on the case's ideal events (no latency: 0 is right): ``ideal_estimate_us``, its mean latency,
    and ``ideal_psnr_change_db``, the EDI PSNR of the ideal events corrected by it minus that of the ideal events
    as they are (what correcting costs, or gains, where there is no latency to correct); NaN if it raises."""
    # the ideal events' own latency is 0 (their meta carries the case's, for the delayed events)
    true = torch.zeros_like(ideal.meta["true_latency"])
    frames = ideal.replace(meta={**ideal.meta, "threshold": case.threshold, "true_latency": true})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the main estimate's warnings are the case's
        try:
            latency = _as_map(estimate(frames), ideal)
        except Exception:  # noqa: BLE001 - reported as NaN; the main estimate's failure is the case's error
            return {"ideal_estimate_us": math.nan, "ideal_psnr_change_db": math.nan}
        change = edi_psnr(ideal, case.threshold, latency.float()) - psnr_ideal
    return {"ideal_estimate_us": float(latency.mean()), "ideal_psnr_change_db": change}


_ESTIMATE_COLUMNS = ("est_latency_us", "est_latency_min_us", "est_latency_max_us", "latency_error_us",
                     "latency_abs_error_us", "latency_bias_us", "psnr_corrected", "recovery", "best_shift_share",
                     "latency_spread_us")


def _estimate_columns(case: Case, delayed: EventFrames, ref: Mapping[str, Any], raw: Any) -> dict[str, float]:
    """The :data:`_ESTIMATE_COLUMNS` of an estimator's answer ``raw``."""
    latency = _as_map(raw, delayed)
    true = delayed.meta["true_latency"].to(torch.float64)
    if case.latency_model == "constant":
        error = float(latency.mean() - true.mean())
        abs_error = abs(error)
    else:
        error = abs_error = float((latency - true).abs().mean())
    psnr_corrected = edi_psnr(delayed, case.threshold, latency.float())
    return {
        "est_latency_us": float(latency.mean()), "est_latency_min_us": float(latency.min()),
        "est_latency_max_us": float(latency.max()), "latency_error_us": error, "latency_abs_error_us": abs_error,
        "latency_bias_us": float(latency.mean() - true.mean()), "psnr_corrected": psnr_corrected,
        "recovery": _gain_ratio(psnr_corrected, ref["psnr_uncorrected"], ref["psnr_ideal"]),
        "best_shift_share": _gain_ratio(psnr_corrected, ref["psnr_uncorrected"], ref["psnr_best_shift"]),
        "latency_spread_us": _spread(raw),
    }


def _spread(raw: Any) -> float:
    """The learned reader's ``meta["latency_spread_us"]`` of an estimator's answer (NaN where it has none)."""
    spread = raw.meta.get("latency_spread_us") if isinstance(raw, EventFrames) else None
    return math.nan if spread is None else float(spread.double().mean())


def _case_columns(case: Case) -> dict[str, Any]:
    d = case.to_dict()
    d["objects"] = " ".join(s if k is None else f"proc-{s}:{k}" for s, k in case.objects)
    d["latency_range_us"] = f"{case.latency_range_us[0]:.0f}-{case.latency_range_us[1]:.0f}"
    d["size"] = f"{case.size[0]}x{case.size[1]}"
    d.update(dark=case.dark, dark_regions=case.dark_regions, noise_models=" ".join(case.noise_models))
    return d


# --- estimators ------------------------------------------------------------------------------------------------------
def corrector_estimator(mode: str = "constant", threshold: float | str = 0.2, **kwargs: Any) -> Estimator:
    """``EventLatencyCorrector(mode, threshold, **kwargs)`` as an estimator (returns its output frames: the suite
    reads their latency map and ``meta["latency_spread_us"]``).

    Example:
        >>> estimate = corrector_estimator("constant", threshold=0.25)
    """
    from evlatcorr.correction import EventLatencyCorrector

    corrector = EventLatencyCorrector(mode=mode, threshold=threshold, **kwargs)

    def estimate(frames: EventFrames) -> EventFrames:
        return corrector(frames)

    return estimate


def load_estimator(spec: str) -> Estimator:
    """Load ``"module:function"`` or ``"path/to/file.py:function"``: a callable ``f(frames) -> latency map``.

    Example:
        >>> load_estimator("evlatcorr.benchmark.accuracy:corrector_estimator")  # doctest: +ELLIPSIS
        <function corrector_estimator at ...>
    """
    if not isinstance(spec, str) or spec.count(":") < 1:
        raise ValueError(f"estimator must be 'module:function' or 'file.py:function', got {spec!r}")
    module_name, _, attr = spec.rpartition(":")
    if module_name.endswith(".py"):
        path = Path(module_name)
        if not path.is_file():
            raise ValueError(f"estimator file {path} does not exist")
        module_spec = importlib.util.spec_from_file_location(path.stem, path)
        if module_spec is None or module_spec.loader is None:
            raise ValueError(f"cannot load {path} as a Python module")
        module = importlib.util.module_from_spec(module_spec)
        module_spec.loader.exec_module(module)
    else:
        module = importlib.import_module(module_name)
    fn = getattr(module, attr, None)
    if not callable(fn):
        raise ValueError(f"{spec}: {attr!r} is not a callable of {module_name}")
    return fn


def run_suite(cases: Sequence[Case], estimators: Mapping[str, Callable[[Case], Estimator]],
              progress: Callable[[str], None] | None = print, before_us: float = 0.0) -> list[dict[str, Any]]:
    """Simulate each case once and evaluate every estimator on it.

    Args:
        cases: the cases.
        estimators: name → factory ``case -> estimator`` (e.g. to pass the case's threshold).
        progress: called with one line per case and estimator; None for silence.
        before_us: the frames also keep this long of events before the exposure (:func:`simulate_case`).

    Returns:
        one :func:`evaluate_case` dict per case and estimator, with ``estimator``, ``sim_time_s``
        and ``reference_time_s`` added.
    """
    results = []
    for k, case in enumerate(cases):
        t0 = time.perf_counter()
        simulated = simulate_case(case, before_us=before_us)
        t1 = time.perf_counter()
        reference = case_reference(case, simulated)
        t2 = time.perf_counter()
        for name, factory in estimators.items():
            row = evaluate_case(case, factory(case), simulated=simulated, reference=reference)
            row.update(estimator=name, sim_time_s=t1 - t0, reference_time_s=t2 - t1)
            results.append(row)
            if progress is not None and row["error"]:
                progress(f"[{k + 1}/{len(cases)}] {name:>8} {case.name}: the estimator failed ({row['error']})")
            elif progress is not None:
                progress(f"[{k + 1}/{len(cases)}] {name:>8} {case.name}: true {row['true_latency_us']:.0f} est "
                         f"{row['est_latency_us']:.0f} err {row['latency_error_us']:+.0f} us, PSNR ideal "
                         f"{row['psnr_ideal']:.2f} uncorr {row['psnr_uncorrected']:.2f} corr "
                         f"{row['psnr_corrected']:.2f}, recovery {_pct(row['recovery'])}; sim {t1 - t0:.1f} s, "
                         f"ref {t2 - t1:.1f} s, estimate {row['time_s']:.1f} s")
    return results


# --- summaries -------------------------------------------------------------------------------------------------------
def _finite(values: Iterable[float]) -> list[float]:
    return [v for v in values if v is not None and not math.isnan(v)]


def _median(values: Iterable[float]) -> float:
    v = _finite(values)
    return statistics.median(v) if v else math.nan


def _group_stats(rows: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    const = [r for r in rows if r["latency_model"] == "constant"]
    gap = [r for r in rows if r["latency_model"] in ("constant", "intensity_delay")]
    photo = [r for r in rows if r["latency_model"] == "intensity"]
    errors = _finite(r["latency_abs_error_us"] for r in const)
    # how far EDI's own PSNR optimum lies from the truth: the floor of a latency error that still buys image quality
    oracle = [abs(r["best_shift_us"] - r["true_latency_us"]) for r in const]
    recovery = _finite(r["recovery"] for r in gap)
    ideal = _finite(r.get("ideal_estimate_us", math.nan) for r in rows)
    ideal_change = sorted(_finite(r.get("ideal_psnr_change_db", math.nan) for r in rows))
    return {
        "cases": len(rows),
        "median_abs_error_us": _median(errors), "worst_abs_error_us": max(errors, default=math.nan),
        "median_best_shift_error_us": _median(oracle),
        "median_map_error_us": _median(r["latency_abs_error_us"] for r in rows if r["latency_model"] != "constant"),
        "median_recovery": _median(recovery), "worst_recovery": min(recovery, default=math.nan),
        "no_gap": sum(bool(r["no_gap"]) for r in gap),
        "median_best_shift_share": _median(r["best_shift_share"] for r in photo),
        "median_const_best_shift_share": _median(r["best_shift_share"] for r in const),
        "median_time_s": _median(r["time_s"] for r in rows),
        "failed": sum(bool(r.get("error")) for r in rows),
        "median_ideal_estimate_us": _median(abs(v) for v in ideal),
        "worst_ideal_estimate_us": max((abs(v) for v in ideal), default=math.nan),
        "ideal_within_150us": sum(abs(v) <= 150.0 for v in ideal), "ideal_cases": len(ideal),
        "mean_ideal_psnr_change_db": statistics.fmean(ideal_change) if ideal_change else math.nan,
        "p10_ideal_psnr_change_db": ideal_change[len(ideal_change) // 10] if ideal_change else math.nan,
        "worst_ideal_psnr_change_db": ideal_change[0] if ideal_change else math.nan,
        "ideal_losing_half_db": sum(v < -0.5 for v in ideal_change),
    }


def warning_kinds(results: Sequence[Mapping[str, Any]]) -> list[tuple[int, str]]:
    """The kinds of warning the estimates raised, most common first: ``(estimates that raised it, an example)``.

    Messages that differ only in their numbers (a sample's times, a latency) are one kind, so the warning every case
    raises by design (the suite's streams stop 15 ms after the exposure) is one line, not one per case.

    Example:
        >>> rows = [{"warnings": ["events end at 49967 us"]}, {"warnings": ["events end at 50012 us", "no minimum"]}]
        >>> warning_kinds(rows)
        [(2, 'events end at 49967 us'), (1, 'no minimum')]

    Raises:
        ValueError: when a row has no list of messages under ``"warnings"``.
    """
    kinds: dict[str, list[Any]] = {}
    for k, row in enumerate(results):
        if not isinstance(row.get("warnings"), (list, tuple)):
            raise ValueError(f"row {k} has no list of messages under 'warnings'")
        for kind, message in {re.sub(r"-?\d[\d.,e+-]*", "#", w): w for w in sorted(row["warnings"])}.items():
            kinds.setdefault(kind, [0, message])[0] += 1
    return sorted(map(tuple, kinds.values()), key=lambda item: (-item[0], item[1]))


def summarize(results: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Aggregates per estimator, split and latency model (and over all models).

    Returns:
        ``{"groups": [{"estimator", "split", "latency_model", "cases", "median_abs_error_us",
        "worst_abs_error_us", "median_best_shift_error_us" (|oracle shift − true|),
        "median_const_best_shift_share" (constant cases), "median_map_error_us" (map cases), "median_recovery",
        "worst_recovery" (constant and intensity_delay cases with a gap), "no_gap",
        "median_best_shift_share" (intensity), "median_time_s", "failed" (cases whose estimator raised; left out
        of the other figures), "median_ideal_estimate_us", "worst_ideal_estimate_us", "ideal_within_150us",
        "ideal_cases" (the estimates on ideal events, whose right answer is 0), "mean_ideal_psnr_change_db",
        "p10_ideal_psnr_change_db", "worst_ideal_psnr_change_db", "ideal_losing_half_db" (the EDI PSNR change of
        the ideal events corrected by that estimate, and the cases where it loses more than 0.5 dB)}, ...],
        "spatial_vs_constant": [...],
        "spread_bands": [...]}``;
        the second lists, for map cases evaluated by both ``"constant"`` and ``"spatial"``, their
        map errors and whether spatial's is lower; the third, the constant-latency cases in three bands of the
        learned reader's spread (``latency_spread_us``) with their errors.
    """
    groups = []
    keys = sorted({(r["estimator"], r["split"]) for r in results}, key=lambda k: (k[0], SPLITS.index(k[1])))
    for estimator, split in keys:
        rows = [r for r in results if r["estimator"] == estimator and r["split"] == split]
        for model in (*LATENCY_MODELS, "all"):
            sub = rows if model == "all" else [r for r in rows if r["latency_model"] == model]
            if sub:
                groups.append({"estimator": estimator, "split": split, "latency_model": model, **_group_stats(sub)})
    by_case: dict[str, dict[str, Mapping[str, Any]]] = {}
    for r in results:
        by_case.setdefault(r["name"], {})[r["estimator"]] = r
    comparison = []
    for name, rows in by_case.items():
        if "constant" in rows and "spatial" in rows and rows["constant"]["latency_model"] != "constant":
            c, s = rows["constant"]["latency_abs_error_us"], rows["spatial"]["latency_abs_error_us"]
            comparison.append({"name": name, "split": rows["constant"]["split"],
                               "latency_model": rows["constant"]["latency_model"], "map_error_constant_us": c,
                               "map_error_spatial_us": s, "spatial_better": s < c,
                               "psnr_constant": rows["constant"]["psnr_corrected"],
                               "psnr_spatial": rows["spatial"]["psnr_corrected"]})
    return {"groups": groups, "spatial_vs_constant": comparison, "spread_bands": _spread_bands(results, keys)}


def _spread_bands(results: Sequence[Mapping[str, Any]], keys: Sequence[tuple[str, str]]) -> list[dict[str, Any]]:
    """Per estimator and split, the constant-latency cases with a spread (:func:`_spread`) in three bands of as many
    cases, from the least to the most spread: does the spread tell a good estimate from a bad one?"""
    bands = []
    for estimator, split in keys:
        rows = sorted((r for r in results if r["estimator"] == estimator and r["split"] == split
                       and r["latency_model"] == "constant" and not math.isnan(r.get("latency_spread_us", math.nan))),
                      key=lambda r: r["latency_spread_us"])
        if len(rows) < 3:
            continue
        for band in range(3):
            part = rows[band * len(rows) // 3:(band + 1) * len(rows) // 3]
            errors = [r["latency_abs_error_us"] for r in part]
            bands.append({"estimator": estimator, "split": split, "band": band + 1, "cases": len(part),
                          "spread_low_us": part[0]["latency_spread_us"],
                          "spread_high_us": part[-1]["latency_spread_us"],
                          "median_abs_error_us": _median(errors), "worst_abs_error_us": max(errors),
                          "over_2ms": sum(e > 2000.0 for e in errors)})
    return bands


def _pct(v: float) -> str:
    return "no gap" if v is None or math.isnan(v) else f"{100 * v:.0f}%"


def _share(v: float) -> str:
    """A summary's ratio: "–" when no case has one."""
    return "–" if v is None or math.isnan(v) else f"{100 * v:.0f}%"


def _num(v: float, digits: int = 0) -> str:
    return "–" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.{digits}f}"


def to_markdown(results: Sequence[Mapping[str, Any]], summary: Mapping[str, Any] | None = None) -> str:
    """Markdown tables: the summary per estimator / split / latency model, then one row per case and estimator."""
    summary = summary if summary is not None else summarize(results)
    lines = ["## Summary", "",
             "| estimator | split | latency model | cases | median abs error µs | worst abs error µs | "
             "median abs error of EDI's best shift µs | median map error µs | median recovery | worst recovery | "
             "no gap | median share of best shift | median time s | failed |",
             "|" + " --- |" * 14]
    for g in summary["groups"]:
        photo = g["latency_model"] == "intensity"
        share = g["median_best_shift_share"] if photo else g["median_const_best_shift_share"]
        lines.append(f"| {g['estimator']} | {g['split']} | {g['latency_model']} | {g['cases']} | "
                     f"{_num(g['median_abs_error_us'])} | {_num(g['worst_abs_error_us'])} | "
                     f"{_num(g['median_best_shift_error_us'])} | {_num(g['median_map_error_us'])} | "
                     f"{_share(g['median_recovery'])} | "
                     f"{_share(g['worst_recovery'])} | {g['no_gap']} | "
                     f"{_share(share)} | "
                     f"{_num(g['median_time_s'], 2)} | {g['failed']} |")
    comparison = summary.get("spatial_vs_constant") or []
    if comparison:
        wins = sum(c["spatial_better"] for c in comparison)
        lines += ["", f"## Spatial vs constant on map cases: spatial has the lower map error on {wins}/"
                  f"{len(comparison)}", "",
                  "| case | latency model | map error constant µs | map error spatial µs | spatial better | "
                  "PSNR constant | PSNR spatial |", "|" + " --- |" * 7]
        for c in comparison:
            lines.append(f"| {c['name']} | {c['latency_model']} | {_num(c['map_error_constant_us'])} | "
                         f"{_num(c['map_error_spatial_us'])} | {'yes' if c['spatial_better'] else 'no'} | "
                         f"{_num(c['psnr_constant'], 2)} | {_num(c['psnr_spatial'], 2)} |")
    ideal = [g for g in summary["groups"] if g["latency_model"] == "all" and g.get("ideal_cases")]
    if ideal:
        lines += ["", "## Ideal events (no latency): the estimate should be 0", "",
                  "EDI PSNR change: the ideal events corrected by the estimate against the ideal events as they are "
                  "(what correcting costs where there is no latency, e.g. in daylight).", "",
                  "| estimator | split | cases | median abs estimate µs | worst µs | within 150 µs | "
                  "EDI PSNR change mean / p10 / worst dB | losing > 0.5 dB |",
                  "|" + " --- |" * 8]
        for g in ideal:
            lines.append(f"| {g['estimator']} | {g['split']} | {g['ideal_cases']} | "
                         f"{_num(g['median_ideal_estimate_us'])} | {_num(g['worst_ideal_estimate_us'])} | "
                         f"{g['ideal_within_150us']} | {_num(g['mean_ideal_psnr_change_db'], 2)} / "
                         f"{_num(g['p10_ideal_psnr_change_db'], 2)} / {_num(g['worst_ideal_psnr_change_db'], 2)} | "
                         f"{g['ideal_losing_half_db']} |")
    if summary.get("spread_bands"):
        lines += ["", "## The learned reader's spread against the error (constant latency)", "",
                  "`meta[\"latency_spread_us\"]`: the standard deviation of the reader's probability over the "
                  "candidates; the cases in three bands of as many cases each.", "",
                  "| estimator | split | band | cases | spread µs | median abs error µs | worst abs error µs | "
                  "error > 2 ms |", "|" + " --- |" * 8]
        for b in summary["spread_bands"]:
            lines.append(f"| {b['estimator']} | {b['split']} | {b['band']} | {b['cases']} | "
                         f"{_num(b['spread_low_us'])}-{_num(b['spread_high_us'])} | {_num(b['median_abs_error_us'])} | "
                         f"{_num(b['worst_abs_error_us'])} | {b['over_2ms']} |")
    lines += ["", "## Cases", "",
              "Error: estimate − true for constant latency, mean |map − true| for the intensity models. "
              "Recovery: (corr − uncorr) / (ideal − uncorr) of EDI PSNR (dB) against the sharp frame. "
              "Best shift: the oracle constant latency whose EDI is closest to the sharp frame (0-15 ms, to 62.5 µs); "
              "its error against the true constant latency is how far EDI's own optimum lies from the truth.", "",
              "| estimator | case | noise | true µs | est µs | error µs | PSNR ideal | uncorr | corr | recovery | "
              "best shift µs / PSNR | share of best | time s |",
              "|" + " --- |" * 13]
    for r in results:
        best = "" if math.isnan(r["psnr_best_shift"]) else f"{r['best_shift_us']:.0f} / {r['psnr_best_shift']:.2f}"
        estimate = (f"{r['est_latency_us']:.0f} | {r['latency_error_us']:+.0f}" if not r.get("error")
                    else f"failed: {r['error']} | –")
        lines.append(f"| {r['estimator']} | {r['name']} | {r['noise_models'] or '–'} | {r['true_latency_us']:.0f} | "
                     f"{estimate} | {r['psnr_ideal']:.2f} | "
                     f"{r['psnr_uncorrected']:.2f} | {_num(r['psnr_corrected'], 2)} | "
                     f"{'–' if r.get('error') else _pct(r['recovery'])} | {best} | "
                     f"{'' if math.isnan(r['psnr_best_shift']) or r.get('error') else _pct(r['best_shift_share'])} | "
                     f"{r['time_s']:.2f} |")
    return "\n".join(lines) + "\n"


def _json_safe(value: Any) -> Any:
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, Mapping):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(v) for v in value]
    return value


def write_results(results: Sequence[Mapping[str, Any]], out_dir: str | Path, summary: Mapping[str, Any] | None = None,
                  header: str = "") -> dict[str, Path]:
    """Write ``results.md`` (``header``, then :func:`to_markdown`), ``results.csv`` and ``results.json`` to ``out_dir``.

    Returns:
        the paths written, by extension.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    summary = summary if summary is not None else summarize(results)
    paths = {"md": out / "results.md", "csv": out / "results.csv", "json": out / "results.json"}
    paths["md"].write_text(header + to_markdown(results, summary))
    columns: list[str] = []
    for r in results:
        columns += [k for k in r if k not in columns]
    with paths["csv"].open("w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=columns)
        writer.writeheader()
        for r in results:
            writer.writerow({k: " | ".join(v) if isinstance(v, list) else v for k, v in r.items()})
    paths["json"].write_text(json.dumps(_json_safe({"results": list(results), "summary": summary}), indent=1))
    return paths
