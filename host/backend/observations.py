"""Bundle-adjustment observation rows held compact: ``(keyframe, point id, cam, u, v, weight)`` with int32
ids, a uint8 camera and float32 pixels and weight, 21 bytes a row instead of the 48 of a float64 row.

A long scan's tracks hold millions of rows; they stay compact in the tracks stage's file and in memory,
and :func:`widened` turns the rows of one adjustment window into the float (N, 6) array the solvers
read (:func:`stereopath.host.backend.ba_common.as_observations`).  float32 keeps a pixel position to
1e-4 px, far below the keypoints' noise.  Pure computation.
"""

from __future__ import annotations

import numpy as np

from stereopath.device.errors import EstimationError

# one compact observation row (packed): keyframe and point id int32, cam uint8, pixels and weight float32
OBSERVATION_DTYPE = np.dtype([("kf", "<i4"), ("point", "<i4"), ("cam", "u1"), ("u", "<f4"), ("v", "<f4"),
                              ("w", "<f4")])
_INT32_MAX = np.iinfo(np.int32).max


def compact_observations(kf: np.ndarray, point: np.ndarray, cam: np.ndarray, uv: np.ndarray,
                         w: np.ndarray) -> np.ndarray:
    """Observation rows as a packed :data:`OBSERVATION_DTYPE` array; EstimationError when an id does
    not fit in int32."""
    kf, point = np.asarray(kf), np.asarray(point)
    for name, ids in (("keyframe index", kf), ("point id", point)):
        if len(ids) and (ids.min() < 0 or ids.max() > _INT32_MAX):
            raise EstimationError(f"{name}s must lie in 0..{_INT32_MAX} for compact observations, "
                                  f"got {ids.min()}..{ids.max()}")
    out = np.empty(len(kf), OBSERVATION_DTYPE)
    out["kf"], out["point"], out["cam"] = kf, point, cam
    uv = np.asarray(uv).reshape(-1, 2)
    out["u"], out["v"], out["w"] = uv[:, 0], uv[:, 1], w
    return out


def observation_keyframes(observations: np.ndarray) -> np.ndarray:
    """The pose index of each observation row (either form), without widening the rows."""
    obs = np.asarray(observations)
    if obs.dtype.names is not None:
        return obs["kf"]
    return obs[:, 0] if obs.ndim == 2 and len(obs) else np.zeros(0)


def widened(observations: np.ndarray) -> np.ndarray:
    """Compact rows as a float (N, 6) array; EstimationError when the rows are not :data:`OBSERVATION_DTYPE`."""
    if observations.dtype != OBSERVATION_DTYPE:
        raise EstimationError(f"compact observations must have the fields {OBSERVATION_DTYPE.names}, "
                              f"got {observations.dtype.names}")
    return np.column_stack([observations[f].astype(float) for f in OBSERVATION_DTYPE.names]).reshape(-1, 6)
