"""Per-frame exposure of the simulated cameras: fixed, slow drift, or an auto-exposure loop.

* fixed: gains (1, 1) and the configured shutter time;
* ``drift`` (``SimConfig.exposure_drift``): slow sinusoidal gain changes and a small left/right
  difference, the shutter time fixed;
* ``auto`` (hand-held trajectories, ``hand_held = True``): the light on the scene changes (a slow
  drift and, every :data:`LIGHT_STEP_S` on average, a step of up to +-:data:`LIGHT_STEP_MAX`
  spread over a few frames, as when the scanner turns towards a lamp or a window) and an
  auto-exposure loop follows it: each frame it moves the shutter time :data:`AE_RATE` of the way
  towards the time that restores the target brightness, within :data:`AE_RANGE_MS`.  Until it
  has caught up the images are brighter or darker (the gain) and the shutter time, hence the
  motion blur, changes from frame to frame.  Deterministic by seed.
"""

from __future__ import annotations

import numpy as np

LIGHT_STEP_S = 2.5
LIGHT_STEP_MAX = 0.35
LIGHT_STEP_FRAMES = 3
AE_RATE = 0.35
AE_RANGE_MS = (2.0, 16.0)
RIGHT_GAIN_SPREAD = 0.03


def drift_gains(t_s: float, seed: int) -> tuple[float, float]:
    """Slow exposure drift gains (left, right) at the frame time ``t_s``."""
    ph = np.random.default_rng([seed & 0xFFFFFFFF, 0xE9]).uniform(0, 2 * np.pi, 3)
    gl = 1.0 + 0.15 * np.sin(2 * np.pi * t_s / 11.0 + ph[0]) + 0.06 * np.sin(2 * np.pi * t_s / 3.7 + ph[1])
    gr = gl * (1.0 + RIGHT_GAIN_SPREAD * np.sin(2 * np.pi * t_s / 5.3 + ph[2]))
    return float(gl), float(gr)


def scene_light(t_s: np.ndarray, seed: int) -> np.ndarray:
    """Relative light on the scene at the frame times ``t_s`` (1 = nominal): drift and smoothed steps."""
    rng = np.random.default_rng([seed & 0xFFFFFFFF, 0xAE])
    ph = rng.uniform(0, 2 * np.pi, 2)
    light = 1.0 + 0.10 * np.sin(2 * np.pi * t_s / 9.0 + ph[0]) + 0.04 * np.sin(2 * np.pi * t_s / 2.9 + ph[1])
    span = float(t_s[-1] - t_s[0]) if len(t_s) > 1 else 0.0
    dt = float(np.median(np.diff(t_s))) if len(t_s) > 1 else 0.05
    n_steps = rng.poisson(span / LIGHT_STEP_S) if span > 0 else 0
    level = np.ones_like(t_s)
    for when, size in zip(rng.uniform(t_s[0], t_s[-1], n_steps), rng.uniform(-LIGHT_STEP_MAX, LIGHT_STEP_MAX, n_steps)):
        ramp = np.clip((t_s - when) / (LIGHT_STEP_FRAMES * dt), 0.0, 1.0)
        level *= 1.0 + size * ramp
    return np.clip(light * level, 0.3, 3.0)


def auto_exposure(t_s: np.ndarray, seed: int, nominal_ms: float) -> tuple[np.ndarray, np.ndarray]:
    """(shutter ms (N,), gains (N, 2)) of an auto-exposure loop under :func:`scene_light` (module doc).

    The gain is the image brightness relative to the target: light * shutter / nominal.
    """
    light = scene_light(t_s, seed)
    lo, hi = AE_RANGE_MS
    shutter = np.empty_like(light)
    e = float(np.clip(nominal_ms / light[0], lo, hi))  # the loop has settled before the first frame
    for i, L in enumerate(light):
        shutter[i] = e
        wanted = np.clip(nominal_ms / L, lo, hi)
        e = float(np.clip(e * (wanted / e) ** AE_RATE, lo, hi))
    gl = light * shutter / nominal_ms
    ph = np.random.default_rng([seed & 0xFFFFFFFF, 0xAF]).uniform(0, 2 * np.pi)
    gr = gl * (1.0 + RIGHT_GAIN_SPREAD * np.sin(2 * np.pi * t_s / 5.3 + ph))
    return shutter, np.stack([gl, gr], 1)
