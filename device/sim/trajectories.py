"""Analytic, smooth camera trajectories with exact first and second derivatives.

A trajectory gives ``T_world_cam0`` (camera-to-world, world z up) at any time ``t_s`` (seconds
since the start of the simulated session, which is also the first IMU sample; the first camera
frame is at ``t_s = 1``), and from closed-form derivatives the camera's linear velocity and
acceleration in the world and its angular velocity and acceleration in the camera frame.  No
finite differences are involved, so the IMU truth built on it is exact.

Structure: ``pose(t) = S(g(t))`` where ``S`` is a *shape* (a path plus an orientation as a chain
of elementary rotations, all sums of sines and closed-form functions of ``g``) and ``g(t)`` a
*time law*:

* still (``g' = 0``) for ``t < STILL_S = 1.25`` s: the rig rests for the first 1.25 s (1 s of
  IMU data before the first camera frame plus the first 0.25 s of frames), for gyro bias and
  gravity estimation at start-up;
* a quintic smooth ramp up to cruise speed (``g' = 1``) over ``RAMP_S = 1.5`` s, cruise, and a
  symmetric ramp down that stops exactly at ``duration_s`` (velocity and acceleration are
  continuous everywhere).

Trajectories (:data:`TRAJECTORIES`, :func:`get_trajectory`):

* ``"arc"`` (default): a handheld arc around the table objects at 0.9-1.2 m radius and
  1.14-1.46 m height, looking at the objects (``TARGET_WORLD``) with camera-frame Euler
  excursions of up to about 20 deg (tilt, about x), 22 deg (pan, y) and 30 deg (roll, z), plus
  hand shake (sum of sines, about 3 mm and 0.5 deg, phases from the seed).  Its cruise speed is
  calibrated so that the default session (400 frames at 20 Hz, ``duration_s = 20.95``) travels
  **5.120 m** measured at the frame times (the paper's 5120 mm).  Other durations follow the
  same arc at the same speed (a shorter session is the beginning of the scan, a longer one goes
  on around the table).
* ``"orbit"``: one full circle (r = 1.1 m, h = 1.35 m) around the objects over the session.
* ``"loop"``: a hand-held walk of :data:`LOOP_TURNS` turns around the room (radius 1.3-1.6 m
  about its centre, at least 0.45 m from the walls; height 1.2-1.45 m) that returns to its start pose
  at the end of the session.  The camera faces along the walk, away from the table, swinging 30 deg
  towards the walls and back once a turn, so it sees walls, corners and floor at 0.5-3 m rather than
  the table objects; camera-frame excursions up to about 10 deg, all periodic over the loop; only
  the hand shake, about 2 mm and 0.3 deg, is not.  Every turn passes the start in the same
  direction (loop closure candidates).  With far and oblique surfaces the on-board path drifts
  more than on turns around the table (whose close objects it keeps seeing): a test case for loop
  closure.
* ``"line"``: a 1 m straight slide past the table with fixed orientation.
* ``"still"``: the arc's start pose, perfectly still (no shake).
* ``"handheld"``: real recorded motion rescaled to a 1.5 m scan, moving from the first IMU sample
  on (no still start, no time law): :mod:`stereopath.device.sim.handheld`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Callable

import numpy as np

from stereopath.device.errors import ConfigError
from stereopath.device.sim.motion import FIRST_FRAME_S, MotionState, rotation_chain
from stereopath.device.sim.scene import TARGET_WORLD

if TYPE_CHECKING:
    from stereopath.device.sim.handheld import HandheldTrajectory

__all__ = ["FIRST_FRAME_S", "MotionState", "TRAJECTORIES", "get_trajectory", "rotation_chain"]

STILL_S = 1.25
RAMP_S = 1.5
DEFAULT_FRAMES = 400
DEFAULT_RATE_HZ = 20.0
DEFAULT_DURATION_S = FIRST_FRAME_S + (DEFAULT_FRAMES - 1) / DEFAULT_RATE_HZ  # 20.95 s
ARC_PATH_LENGTH_M = 5.12

# camera looking along world +x with z up: camera x (right) = -y, y (down) = -z, z (forward) = +x
_R_BASE = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


# ----------------------------------------------------------------------------------- helpers


class Sines:
    """``f(g) = sum_i a_i sin(2 pi f_i g + p_i)`` with its first two derivatives."""

    def __init__(self, amps, freqs_hz, phases=None) -> None:
        self.a = np.asarray(amps, float).reshape(-1)
        self.w = 2 * np.pi * np.asarray(freqs_hz, float).reshape(-1)
        self.p = np.zeros_like(self.a) if phases is None else np.asarray(phases, float).reshape(-1)

    def __call__(self, g: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        arg = np.outer(g, self.w) + self.p
        s, c = np.sin(arg), np.cos(arg)
        return s @ self.a, c @ (self.a * self.w), -(s @ (self.a * self.w**2))


def _smootherstep(u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """S(u) = 6u^5 - 15u^4 + 10u^3, its derivative and its integral from 0."""
    return (u**3 * (6 * u**2 - 15 * u + 10), 30 * u**2 * (1 - u) ** 2, u**4 * (u**2 - 3 * u + 2.5))


class TimeLaw:
    """``g(t)``: still until ``still_s``, quintic ramp to ``g' = 1``, cruise, ramp down to rest at ``end_s``."""

    def __init__(self, end_s: float, still_s: float = STILL_S, ramp_s: float = RAMP_S) -> None:
        self.still_s = float(still_s)
        if not np.isfinite(self.still_s):  # never moves
            self.end_s, self.ramp_s, self.g_end = self.still_s, 0.0, 0.0
            return
        self.end_s = max(float(end_s), self.still_s)
        self.ramp_s = min(float(ramp_s), (self.end_s - self.still_s) / 2)
        self.g_end = (self.end_s - self.still_s) - self.ramp_s

    def __call__(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        t = np.asarray(t, float)
        g = np.zeros_like(t)
        e = np.zeros_like(t)
        de = np.zeros_like(t)
        T = self.ramp_s
        if T <= 0:
            return g, e, de
        t0, t1 = self.still_s, self.end_s
        up = (t > t0) & (t < t0 + T)
        cruise = (t >= t0 + T) & (t <= t1 - T)
        down = (t > t1 - T) & (t < t1)
        after = t >= t1
        u = (t[up] - t0) / T
        S, dS, IS = _smootherstep(u)
        g[up], e[up], de[up] = T * IS, S, dS / T
        g[cruise], e[cruise] = 0.5 * T + (t[cruise] - t0 - T), 1.0
        u = (t1 - t[down]) / T
        S, dS, IS = _smootherstep(u)
        g[down], e[down], de[down] = self.g_end - T * IS, S, -dS / T
        g[after] = self.g_end
        return g, e, de


# ----------------------------------------------------------------------------------- shapes


class Shape:
    """A path and orientation as functions of the motion parameter ``g``."""

    def position(self, g: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # (N,3) x3
        raise NotImplementedError

    def rotation_factors(self, g: np.ndarray) -> list[tuple]:
        """List of ("const", R) or (axis, theta, dtheta/dg, d2theta/dg2)."""
        raise NotImplementedError


def _shake(seed: int, amp_pos_m: float, amp_rot_deg: float) -> tuple[list[Sines], list[Sines]]:
    rng = np.random.default_rng([int(seed) & 0xFFFFFFFF, 0x5A4E])
    pos = [Sines(amp_pos_m * np.array([0.55, 0.3, 0.15]), [0.9, 1.7, 3.1] * (1 + 0.1 * rng.random(3)),
                 rng.uniform(0, 2 * np.pi, 3)) for _ in range(3)]
    rot = [Sines(np.radians(amp_rot_deg) * np.array([0.55, 0.3, 0.15]), [1.3, 2.3, 4.1] * (1 + 0.1 * rng.random(3)),
                 rng.uniform(0, 2 * np.pi, 3)) for _ in range(3)]
    return pos, rot


def _pitch_down(u, du, ddu, w, dw, ddw):
    """theta = atan2(u, w) (u = height above target, w = horizontal distance) and derivatives."""
    th = np.arctan2(u, w)
    D = w**2 + u**2
    N = w * du - u * dw
    dN = w * ddu - u * ddw
    dD = 2 * (w * dw + u * du)
    return th, N / D, (dN * D - N * dD) / D**2


class LookAtOrbitShape(Shape):
    """Camera on ``(r cos phi, r sin phi, h)`` around the z axis looking at ``TARGET_WORLD`` (+ excursions)."""

    def __init__(self, phi0: float, k: float, radius: tuple[Sines, float], height: tuple[Sines, float],
                 excursions: tuple[Sines, Sines, Sines] | None, shake: tuple[list[Sines], list[Sines]] | None,
                 yaw_offset: Sines | None = None) -> None:
        """``radius`` and ``height``: (variation, mean); ``shake``: (position, rotation) sums of sines or None."""
        self.phi0, self.k = float(phi0), float(k)
        self.yaw_offset = yaw_offset  # heading away from the target (0: looking at it), a function of g
        self.r, self.r0 = radius[0], float(radius[1])
        self.h, self.h0 = height[0], float(height[1])
        self.exc = excursions
        self.shake_pos, self.shake_rot = shake if shake is not None else (None, None)

    def _rh(self, g):
        r, dr, ddr = self.r(g)
        h, dh, ddh = self.h(g)
        return r + self.r0, dr, ddr, h + self.h0, dh, ddh

    def position(self, g):
        r, dr, ddr, h, dh, ddh = self._rh(g)
        phi = self.phi0 + self.k * g
        k = self.k
        c, s = np.cos(phi), np.sin(phi)
        P = np.stack([r * c, r * s, h], 1)
        dP = np.stack([dr * c - r * k * s, dr * s + r * k * c, dh], 1)
        ddP = np.stack([ddr * c - 2 * dr * k * s - r * k * k * c, ddr * s + 2 * dr * k * c - r * k * k * s, ddh], 1)
        _add_shake(P, dP, ddP, self.shake_pos, g)
        return P, dP, ddP

    def rotation_factors(self, g):
        n = len(g)
        r, dr, ddr, h, dh, ddh = self._rh(g)
        zt = TARGET_WORLD[2]
        pitch, dpitch, ddpitch = _pitch_down(h - zt, dh, ddh, r, dr, ddr)
        yaw = self.phi0 + self.k * g + np.pi
        zeros = np.zeros(n)
        dyaw, ddyaw = np.full(n, self.k), zeros
        if self.yaw_offset is not None:
            off, doff, ddoff = self.yaw_offset(g)
            yaw, dyaw, ddyaw = yaw + off, dyaw + doff, ddoff
        ax = [-pitch, -dpitch, -ddpitch]
        ay = [zeros.copy(), zeros.copy(), zeros.copy()]
        az = [zeros.copy(), zeros.copy(), zeros.copy()]
        for dst, srcs in ((ax, 0), (ay, 1), (az, 2)):
            for group in (self.exc, self.shake_rot):
                if group is None:
                    continue
                vals = group[srcs](g)
                for j in range(3):
                    dst[j] = dst[j] + vals[j]
        return [("z", yaw, dyaw, ddyaw), ("const", _R_BASE), ("x", *ax), ("y", *ay), ("z", *az)]


def _add_shake(P, dP, ddP, shake_pos, g) -> None:
    """Add hand shake (per-axis sums of sines with analytic derivatives) to a position track."""
    if shake_pos is None:
        return
    for i, sh in enumerate(shake_pos):
        a, da, dda = sh(g)
        P[:, i] += a
        dP[:, i] += da
        ddP[:, i] += dda


class LineShape(Shape):
    """A straight slide ``p0 + dir * speed * g`` with a fixed orientation looking at the table."""

    def __init__(self, p0, direction, speed: float, yaw: float, pitch_down: float,
                 shake_pos: list[Sines] | None, shake_rot: list[Sines] | None) -> None:
        self.p0 = np.asarray(p0, float)
        d = np.asarray(direction, float)
        self.d = d / np.linalg.norm(d)
        self.speed = float(speed)
        self.yaw, self.pitch = float(yaw), float(pitch_down)
        self.shake_pos, self.shake_rot = shake_pos, shake_rot

    def position(self, g):
        n = len(g)
        P = self.p0 + np.outer(g * self.speed, self.d)
        dP = np.tile(self.d * self.speed, (n, 1))
        ddP = np.zeros((n, 3))
        _add_shake(P, dP, ddP, self.shake_pos, g)
        return P, dP, ddP

    def rotation_factors(self, g):
        n = len(g)
        z = np.zeros(n)
        angles = [[np.full(n, -self.pitch), z.copy(), z.copy()], [z.copy(), z.copy(), z.copy()], [z.copy(), z.copy(), z.copy()]]
        if self.shake_rot is not None:
            for i in range(3):
                v = self.shake_rot[i](g)
                angles[i] = [angles[i][j] + v[j] for j in range(3)]
        return [("z", np.full(n, self.yaw), z, z), ("const", _R_BASE), ("x", *angles[0]), ("y", *angles[1]),
                ("z", *angles[2])]


# ----------------------------------------------------------------------------------- trajectory


class AnalyticTrajectory:
    """``pose(t) = shape(g(t))`` with exact derivatives (see the module doc)."""

    def __init__(self, name: str, shape: Shape, law: TimeLaw, duration_s: float) -> None:
        self.name = name
        self.shape = shape
        self.law = law
        self.duration_s = float(duration_s)

    def state(self, t_s) -> MotionState:
        t = np.atleast_1d(np.asarray(t_s, float))
        g, e, de = self.law(t)
        P, dP, ddP = self.shape.position(g)
        v = dP * e[:, None]
        a = ddP * (e**2)[:, None] + dP * de[:, None]
        factors = []
        for f in self.shape.rotation_factors(g):
            if f[0] == "const":
                factors.append(f)
            else:
                axis, th, dth, ddth = f
                factors.append((axis, th, dth * e, ddth * e**2 + dth * de))
        R, w, al = rotation_chain(factors, len(t))
        return MotionState(t, R, P, v, a, w, al)

    def pose(self, t_s):
        """``T_world_cam0`` (4, 4) for a scalar time, (N, 4, 4) for an array."""
        T = self.state(t_s).T_world_cam
        return T[0] if np.ndim(t_s) == 0 else T

    def angular_velocity_cam(self, t_s) -> np.ndarray:
        return self.state(t_s).omega_cam

    def acceleration_world(self, t_s) -> np.ndarray:
        return self.state(t_s).a_world

    def velocity_world(self, t_s) -> np.ndarray:
        return self.state(t_s).v_world

    def path_length_m(self, t_s: np.ndarray) -> float:
        """Length of the polyline through the positions at the times ``t_s``."""
        p = self.shape.position(self.law(np.asarray(t_s, float))[0])[0]
        return float(np.sum(np.linalg.norm(np.diff(p, axis=0), axis=1)))


def default_frame_times(frames: int = DEFAULT_FRAMES, rate_hz: float = DEFAULT_RATE_HZ) -> np.ndarray:
    return FIRST_FRAME_S + np.arange(frames) / rate_hz


def _arc_shape(k: float, seed: int, shake: bool = True) -> LookAtOrbitShape:
    exc = (
        Sines(np.radians([16.0, 6.0]), [1 / 11.0, 1 / 4.3], [0.2, 3.0]),   # tilt (camera x)
        Sines(np.radians([17.0, 7.0]), [1 / 8.5, 1 / 3.3], [3.3, 0.2]),    # pan (camera y)
        Sines(np.radians([22.0, 8.0]), [1 / 10.0, 1 / 3.9], [0.9, 2.6]),   # roll (camera z)
    )
    return LookAtOrbitShape(
        phi0=np.radians(-115.0), k=k,
        radius=(Sines([0.12, 0.03], [1 / 13.0, 1 / 5.1], [0.3, 1.0]), 1.05),
        height=(Sines([0.12, 0.04], [1 / 9.0, 1 / 3.7], [1.1, 0.2]), 1.30),
        excursions=exc, shake=_shake(seed, 0.003, 0.5) if shake else None,
    )


def make_arc(duration_s: float = DEFAULT_DURATION_S, seed: int = 0,
             path_length_m: float = ARC_PATH_LENGTH_M) -> AnalyticTrajectory:
    """The default handheld arc; its speed makes the default session travel ``path_length_m``."""
    law_ref = TimeLaw(DEFAULT_DURATION_S)
    t_ref = default_frame_times()

    def length(k: float) -> float:
        return AnalyticTrajectory("arc", _arc_shape(k, seed), law_ref, DEFAULT_DURATION_S).path_length_m(t_ref)

    lo, hi = 0.01, 1.0
    for _ in range(60):  # bisection: the length grows with the angular speed k
        mid = 0.5 * (lo + hi)
        if length(mid) < path_length_m:
            lo = mid
        else:
            hi = mid
    k = 0.5 * (lo + hi)
    return AnalyticTrajectory("arc", _arc_shape(k, seed), TimeLaw(duration_s), duration_s)


def make_orbit(duration_s: float = DEFAULT_DURATION_S, seed: int = 0) -> AnalyticTrajectory:
    law = TimeLaw(duration_s)
    k = 2 * np.pi / law.g_end if law.g_end > 0 else 0.0
    shape = LookAtOrbitShape(np.radians(-90.0), k, (Sines([0.0], [0.0]), 1.1), (Sines([0.0], [0.0]), 1.35), None,
                             _shake(seed, 0.002, 0.3))
    return AnalyticTrajectory("orbit", shape, law, duration_s)


LOOP_TURNS = 2
LOOP_RADIUS_M = 1.45


def make_loop(duration_s: float = DEFAULT_DURATION_S, seed: int = 0, turns: int = LOOP_TURNS,
              radius_m: float = LOOP_RADIUS_M) -> AnalyticTrajectory:
    """``turns`` walks around the room, back to the start pose at ``duration_s`` (module doc)."""
    law = TimeLaw(duration_s)
    G = law.g_end if law.g_end > 0 else 1.0
    k = 2 * np.pi * turns / G if law.g_end > 0 else 0.0
    per = np.array([1.0, 2.0, 3.0, 5.0, 7.0]) / G  # whole cycles over the loop: the path closes
    sp, sr = _shake(seed, 0.002, 0.3)
    exc = (
        Sines(np.radians([8.0, 3.0]), per[[1, 4]], [0.2, 3.0]),   # tilt (camera x)
        Sines(np.radians([9.0, 3.0]), per[[2, 3]], [3.3, 0.2]),   # pan (camera y)
        Sines(np.radians([10.0, 4.0]), per[[0, 3]], [0.9, 2.6]),  # roll (camera z)
    )
    # heading: along the walk (90 deg off the table), swinging 30 deg towards the walls and back once a turn
    heading = Sines(np.radians([90.0, 30.0]), [0.0, turns / G], [np.pi / 2, 0.0])
    shape = LookAtOrbitShape(np.radians(-100.0), k, (Sines([0.10, 0.03], per[[2, 4]], [0.3, 1.0]), radius_m),
                             (Sines([0.09, 0.03], per[[1, 3]], [1.1, 0.2]), 1.32), exc, (sp, sr), yaw_offset=heading)
    return AnalyticTrajectory("loop", shape, law, duration_s)


def make_line(duration_s: float = DEFAULT_DURATION_S, seed: int = 0, length_m: float = 1.0) -> AnalyticTrajectory:
    law = TimeLaw(duration_s)
    speed = length_m / law.g_end if law.g_end > 0 else 0.0
    sp, sr = _shake(seed, 0.002, 0.3)
    p0 = np.array([-length_m / 2, -1.1, 1.3])
    pitch = float(np.arctan2(p0[2] - TARGET_WORLD[2], 1.1))
    shape = LineShape(p0, (1.0, 0.0, 0.0), speed, yaw=np.pi / 2, pitch_down=pitch, shake_pos=sp, shake_rot=sr)
    return AnalyticTrajectory("line", shape, law, duration_s)


def make_still(duration_s: float = DEFAULT_DURATION_S, seed: int = 0) -> AnalyticTrajectory:
    shape = _arc_shape(0.3, seed, shake=False)
    return AnalyticTrajectory("still", shape, TimeLaw(0.0, still_s=np.inf), duration_s)


def make_handheld(duration_s: float = DEFAULT_DURATION_S, seed: int = 0) -> HandheldTrajectory:
    """Real recorded motion as a hand-held scan (:mod:`stereopath.device.sim.handheld`)."""
    from stereopath.device.sim.handheld import HandheldTrajectory

    return HandheldTrajectory(duration_s)


TRAJECTORIES: dict[str, Callable[..., AnalyticTrajectory | HandheldTrajectory]] = {
    "arc": make_arc,
    "orbit": make_orbit,
    "loop": make_loop,
    "line": make_line,
    "still": make_still,
    "handheld": make_handheld,
}


def get_trajectory(name: str, duration_s: float = DEFAULT_DURATION_S,
                   seed: int = 0) -> AnalyticTrajectory | HandheldTrajectory:
    """The trajectory ``name`` (a key of :data:`TRAJECTORIES`) lasting ``duration_s`` seconds."""
    if name not in TRAJECTORIES:
        raise ConfigError(f"trajectory = {name!r} is unknown; choose one of {', '.join(TRAJECTORIES)}")
    if not np.isfinite(duration_s) or duration_s <= 0:
        raise ConfigError(f"trajectory duration_s = {duration_s!r} must be positive")
    return TRAJECTORIES[name](duration_s=float(duration_s), seed=int(seed))
