"""Camera conventions of the export formats (pure: arrays in, arrays out).

Our poses are ``T_world_cam`` (camera to world) with OpenCV camera axes: x right, y down, z
forward.  The stereo rig maps camera-0 coordinates into camera 1 with ``X1 = R X0 + T``
(:class:`stereopath.device.core.rig.Rig`).

* COLMAP stores ``cam_from_world`` (world to camera, OpenCV axes); a rig stores each sensor's
  ``sensor_from_rig`` with the rig frame = camera 0.
* nerfstudio's ``transform_matrix`` is camera to world with OpenGL camera axes: x right, y up,
  z backward (the camera looks along -z).  Its own COLMAP converter
  (``nerfstudio/process_data/colmap_utils.py: colmap_to_json``) builds it as ``inv(w2c)`` with
  columns 1 and 2 negated; :func:`opengl_from_opencv` does the same.
"""

from __future__ import annotations

import numpy as np

from stereopath.device.core.geometry import invert_pose

# camera axes OpenCV -> OpenGL: y and z flipped (its own inverse)
CV_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])


def opengl_from_opencv(T_world_cam: np.ndarray) -> np.ndarray:
    """Camera-to-world poses (..., 4, 4) with OpenCV camera axes -> the same cameras with OpenGL axes."""
    return np.asarray(T_world_cam, float) @ CV_TO_GL


def opencv_from_opengl(T_world_cam_gl: np.ndarray) -> np.ndarray:
    """The inverse of :func:`opengl_from_opencv`."""
    return np.asarray(T_world_cam_gl, float) @ CV_TO_GL


def T_cam1_cam0(R: np.ndarray, T: np.ndarray) -> np.ndarray:
    """The 4x4 transform taking camera-0 coordinates into camera 1 (``X1 = R X0 + T``)."""
    out = np.eye(4)
    out[:3, :3] = np.asarray(R, float)
    out[:3, 3] = np.asarray(T, float).reshape(3)
    return out


def T_world_cam1(T_world_cam0: np.ndarray, R: np.ndarray, T: np.ndarray) -> np.ndarray:
    """Camera-1 poses (..., 4, 4) of camera-0 poses for a rig (``X1 = R X0 + T``)."""
    return np.asarray(T_world_cam0, float) @ invert_pose(T_cam1_cam0(R, T))


def project_pinhole(K: np.ndarray, T_world_cam: np.ndarray, X_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (N, 2) of world points (N, 3) in a pinhole camera (OpenCV axes) and the mask of points in front."""
    T_cam_world = invert_pose(np.asarray(T_world_cam, float))
    Xc = np.asarray(X_world, float) @ T_cam_world[:3, :3].T + T_cam_world[:3, 3]
    front = Xc[:, 2] > 1e-9
    z = np.where(front, Xc[:, 2], 1.0)
    uv = np.column_stack([K[0, 0] * Xc[:, 0] / z + K[0, 2], K[1, 1] * Xc[:, 1] / z + K[1, 2]])
    return uv, front


def project_opengl(fl: tuple[float, float], c: tuple[float, float], T_world_cam_gl: np.ndarray,
                   X_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels (N, 2) of world points in a camera given as nerfstudio gives it (OpenGL camera to world,
    ``fl_x, fl_y``, ``cx, cy``; pixel rows grow downward) and the mask of points in front (z < 0)."""
    T_cam_world = invert_pose(np.asarray(T_world_cam_gl, float))
    Xc = np.asarray(X_world, float) @ T_cam_world[:3, :3].T + T_cam_world[:3, 3]
    front = Xc[:, 2] < -1e-9
    z = np.where(front, -Xc[:, 2], 1.0)
    uv = np.column_stack([fl[0] * Xc[:, 0] / z + c[0], -fl[1] * Xc[:, 1] / z + c[1]])
    return uv, front
