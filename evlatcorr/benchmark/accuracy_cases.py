"""The accuracy suite's cases (:mod:`evlatcorr.benchmark.accuracy`): seeded one-frame scenes, and their simulation.

Each split is drawn from its own fixed seed. Each factor (scene, dark background, brightness, motion kind, speed,
direction, latency model, latency, each noise model, threshold) is drawn from its own generator stream, categorical
factors as a shuffled balanced list, so every split covers every procedural kind, motion kind, latency model and
noise model, and dark scenes. A case is a 20 ms exposure of a ``(96, 128)`` sensor whose events stop 15 ms after the
exposure's end.

Example:
    >>> case = make_cases("test", num=1)[0]
    >>> case.split, case.size
    ('test', (96, 128))
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from evlatcorr.frames import EventFrames
from evlatcorr.scenes import PROCEDURAL_SCENES, procedural_scene
from evlatcorr.simulate import PHOTOGRAPHS_TEST, PHOTOGRAPHS_TRAIN, ObjectSpec, SimulatedSequence, simulate

__all__ = ["SPLITS", "LATENCY_MODELS", "MOTION_KINDS", "DEFAULT_SIZE", "TRAIN_SPLITS", "DELAY_TRAIN_SPLIT", "Case",
           "at_exposure", "make_cases", "simulate_case"]


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
# and the tile reader's (evlatcorr.tile_reader), beside those: 300 per-pixel delay cases of the same photographs
DELAY_TRAIN_SPLIT = "train_delay"
_NUM_CASES = {"dev": 40, "dev_wide": 120, "test": 48, "train": 200, "train1": 300, "train2": 400, "train3": 900,
              "train_photo": 200, DELAY_TRAIN_SPLIT: 300}
_PHOTOGRAPHS = {"dev": PHOTOGRAPHS_TRAIN, "dev_wide": PHOTOGRAPHS_TRAIN, "test": PHOTOGRAPHS_TEST,
                **{s: PHOTOGRAPHS_TRAIN for s in (*TRAIN_SPLITS, DELAY_TRAIN_SPLIT)}}
# case draws: generator seed 1000 * split seed + factor index
_SPLIT_SEED = {"dev": 1, "test": 2, "train": 3, "train1": 4, "train2": 5, "train3": 6, "train_photo": 7, "dev_wide": 11,
               DELAY_TRAIN_SPLIT: 13}
# procedural scenes and sprites: disjoint seed ranges
_SCENE_SEED = {"dev": 100_000, "test": 200_000, "train": 300_000, "train1": 400_000, "train2": 500_000,
               "train3": 600_000, "train_photo": 700_000, "dev_wide": 1_100_000, DELAY_TRAIN_SPLIT: 1_300_000}
_SIM_SEED = {"dev": 10_000, "test": 20_000, "train": 30_000, "train1": 40_000, "train2": 50_000, "train3": 60_000,
             "train_photo": 70_000, "dev_wide": 110_000, DELAY_TRAIN_SPLIT: 130_000}
_MOTION_WEIGHTS = (0.3, 0.15, 0.2, 0.15, 0.2)
_LATENCY_WEIGHTS = (0.5, 0.25, 0.25)
_TRAIN_LATENCY_WEIGHTS = (1.0, 0.0, 0.0)
_SPLIT_LATENCY_WEIGHTS = {"train_photo": (0.0, 0.0, 1.0), DELAY_TRAIN_SPLIT: (0.0, 1.0, 0.0)}
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
            trained on; never reported), or :data:`DELAY_TRAIN_SPLIT` (per-pixel delay: the tile reader's too).
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
    if split not in (*SPLITS, *TRAIN_SPLITS, DELAY_TRAIN_SPLIT):
        raise ValueError(f"split must be one of {(*SPLITS, *TRAIN_SPLITS, DELAY_TRAIN_SPLIT)}, got {split!r}")
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


def at_exposure(case: Case, exposure_us: float) -> Case:
    """The case at another exposure time, its latencies and the events' run-on after the exposure scaled with it
    (dimmer light: longer exposures and later events), its scene, motion (px/ms) and noise kept.

    The suite draws every case at a 20 ms exposure, the learned readers' training too: this asks whether the
    estimate holds at others. The case's name gets the exposure in ms.

    Example:
        >>> case = at_exposure(make_cases("test", num=1)[0], 10_000.0)
        >>> case.name.endswith("-e10ms"), case.exposure_us, case.after_us
        (True, 10000.0, 7500.0)
    """
    if not (math.isfinite(exposure_us) and exposure_us > 0):
        raise ValueError(f"exposure_us must be a positive number of µs, got {exposure_us}")
    scale = exposure_us / case.exposure_us
    return dataclasses.replace(
        case, name=f"{case.name}-e{exposure_us / 1000:g}ms", exposure_us=float(exposure_us),
        latency_us=case.latency_us * scale, latency_range_us=tuple(v * scale for v in case.latency_range_us),
        after_us=case.after_us * scale)


def simulate_case(case: Case, num_frames: int = 1, before_us: float = 0.0, frame_interval_us: float | None = None
                  ) -> tuple[EventFrames, EventFrames, SimulatedSequence]:
    """Simulate a case.

    Args:
        case: the case.
        num_frames: frames of the case's scene and motion, back to back (each exposure starts where the previous
            one ends): a sequence of one recording, for :mod:`evlatcorr.temporal`. Its first frame is not the
            one-frame case's: the simulator draws noise and random motion over the whole sequence.
        before_us: the frames also keep the events of this long before each exposure (as a recording's stream
            has them; the simulation is the same), at most ``case.after_us``.
        frame_interval_us: time from one exposure's start to the next (default: the exposure time, back to back;
            a camera's frames have a gap between them).

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
    interval = case.exposure_us if frame_interval_us is None else float(frame_interval_us)
    if not (math.isfinite(interval) and interval >= case.exposure_us):
        raise ValueError(f"frame_interval_us must be at least the exposure time {case.exposure_us} us, got "
                         f"{frame_interval_us}")
    kwargs: dict[str, Any] = dict(
        num_frames=num_frames, height=case.size[0], width=case.size[1], exposure_us=case.exposure_us,
        frame_interval_us=interval, latency=case.latency_model, latency_us=case.latency_us,
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
