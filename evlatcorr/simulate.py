"""Public facade of the event simulator (implemented in :mod:`evlatcorr.simulation`): import from here.

An event simulator with known latency, from the photographs scikit-image ships.

A photograph is seen by a camera under a random smooth motion: a drift in a random direction with
a gentle wobble (sums of low-frequency sinusoids), a small rotation and a small zoom, rendered
with Kornia's ``warp_affine``. At small time steps (≤ 0.3 px of image motion per step) the
simulator renders the luminance ``Y = 0.299 R + 0.587 G + 0.114 B`` and emits an event each time
``log(Y + 1e-3)`` of a pixel crosses a multiple of the contrast threshold away from its last
event's level, the crossing time interpolated linearly inside the step (as ESIM does). Colour is
kept for the frames: blurry frames are the time average of the colour frames over each exposure
(exact for frames varying linearly between steps), sharp frames are rendered at mid-exposure and
at any requested time.

Latency models (``latency=``):

- ``"none"``: delayed events are the ideal events.
- ``"constant"``: delayed events are the ideal events stamped ``latency_us`` later.
- ``"intensity"``: each pixel's photoreceptor is a first-order low-pass filter on the log-luminance
  whose time constant is inversely proportional to the pixel's linear intensity ``I`` in [0, 1]
  (as in v2e and IEBCS), ``τ = clip(latency_range_us[0] / I, *latency_range_us)``: bright pixels
  (I = 1) lag by ``latency_range_us[0]`` (0.5 ms by default), dim ones up to
  ``latency_range_us[1]`` (10 ms). The filter is updated exactly for an input that is linear
  between steps, and it is run over a warm-up of ``4 τ_max`` before the first event so it starts
  in its steady state. The delayed events are the threshold crossings of the *filtered* signal;
  the ideal events those of the unfiltered one. A first-order filter following a ramp lags it by
  exactly ``τ`` (and, for any monotone change, the level-crossing times lag by ``τ`` on average),
  so the true latency map reported is ``τ`` at the pixel's intensity averaged over the exposure,
  i.e. computed from the blurry frame's luminance: the quantity a method can estimate from it.
- ``"intensity_delay"``: each ideal event is delayed by that same map (of the frame nearest in
  time) at its pixel: an exact per-pixel ground truth, without the filter's smoothing.

Motion (``motion=``): ``"random"`` (above), a constant translation ``(vx, vy)`` px/ms, ``"rotation"``
(about the view's centre) or ``"zoom"`` (about the view's centre), both at ``max_speed_px_per_ms``
at the view's corners, in a random direction. With ``objects=`` (:class:`ObjectSpec`) the camera is
static and sprites with soft-edged masks move at constant velocities over the background.

Noise, the same in both streams (ideal and delayed differ only by the latency):

- ``noise_rate_hz``: shot noise, Poisson events of random polarity at uniform times, undelayed;
- ``leak_rate_hz``: leak events, ON events repeating at each pixel with a period drawn around
  ``1 / leak_rate_hz`` (lognormal rates) and a random phase, undelayed;
- ``threshold_sigma``: per-pixel contrast-threshold mismatch;
- ``refractory_us``: an event is dropped when the previous event of its pixel (in the stream's own
  times, noise included) is less than ``refractory_us`` earlier (see :func:`apply_refractory`).

Everything random comes from one ``torch.Generator`` seeded by ``seed``, so a seed gives identical
events.

The implementation, one concern per module of :mod:`evlatcorr.simulation`: ``photographs``
(source images), ``motion`` (camera trajectories and views), ``objects`` (sprites over a still
background), ``generator`` (thresholds and crossings), ``latency`` (latency models), ``noise``,
``settings``, ``timeline``, ``stepping`` (the time loop), ``sequence`` and ``simulator``.
"""

from __future__ import annotations

# MAX_LATENCY_US and OBJECT_SHAPES were public names of this module before the split: still importable here
from evlatcorr.simulation.latency import LATENCY_MODELS
from evlatcorr.simulation.latency import MAX_LATENCY_US as MAX_LATENCY_US
from evlatcorr.simulation.motion import MOTIONS
from evlatcorr.simulation.noise import apply_refractory
from evlatcorr.simulation.objects import OBJECT_SHAPES as OBJECT_SHAPES
from evlatcorr.simulation.objects import ObjectSpec
from evlatcorr.simulation.photographs import PHOTOGRAPHS_TEST, PHOTOGRAPHS_TRAIN, load_photograph, luminance
from evlatcorr.simulation.sequence import SimulatedSequence
from evlatcorr.simulation.simulator import simulate, simulate_dataset

__all__ = [
    "PHOTOGRAPHS_TRAIN",
    "PHOTOGRAPHS_TEST",
    "LATENCY_MODELS",
    "MOTIONS",
    "ObjectSpec",
    "apply_refractory",
    "load_photograph",
    "luminance",
    "simulate",
    "simulate_dataset",
    "SimulatedSequence",
]
