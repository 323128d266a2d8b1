"""Instantaneous time to collision per lidar ray, and the brake decision (no I/O).

Per ray (F1TENTH safety node, corrected for where the car's body is): a static point at range r
in direction theta (car frame) closes at v cos(theta) when the car drives straight at speed v, and
the car's body box starts ``CarParams.ray_start_offsets(theta)`` along that ray from the lidar,
so

    iTTC = max(r - offset(theta), 0) / max(v cos(theta), eps)

A scan's value is its ``min_rays``-th smallest iTTC. :class:`BrakeLogic` brakes when that value is
below ``threshold_s`` for ``debounce_scans`` scans in a row and releases with hysteresis: the
value, computed at ``max(v, release_probe_mps)``, above ``release_s`` for ``release_scans`` scans
in a row, and at least ``min_brake_s`` after the brake began. The probe speed matters once the
brake has stopped the car: it stays braked while the way ahead is too short to drive off at the
probe speed (a crossing car still in front, a wall), instead of releasing at standstill and
letting the controller creep into it brake after brake. At each brake it also asks whether any point that triggered it lies in the
car's straight-ahead swept box (widened by ``lateral_margin_m``); if none does, the brake is a
false-brake candidate (a wall beside the path, a bend): counted, not suppressed.

``path_gate`` optionally restricts the rays that may brake to hit points in the band the car's
body sweeps: "straight" (the box ahead) or "arc" (keeping the current steering angle, kinematic
single track). The iTTC of a ray is the same formula either way; the gate only removes rays
that point at something the car will pass (corridor walls, the outside wall of a bend).
"""

from __future__ import annotations

import numpy as np

from racecav.common.config import SafetyConfig
from racecav.common.vehicle import CarParams


class RayGeometry:
    """Per-ray constants of one scan layout: body offset, direction in the car frame.

    :param car: car parameters (lidar mount, body box).
    :param angles: ray angles in the laser frame (rad).
    """

    def __init__(self, car: CarParams, angles: np.ndarray):
        m = car.lidar_mount
        theta = np.asarray(angles, np.float64) + m.yaw
        self.offset = car.ray_start_offsets(np.asarray(angles, np.float64))
        self.cos, self.sin = np.cos(theta), np.sin(theta)
        self.mount_x, self.mount_y = m.x, m.y
        self.half_length, self.half_width = car.length / 2, car.width / 2
        self.rear_axle = car.wheelbase / 2  # the car frame's origin is midway between the axles
        self.wheelbase = car.wheelbase

    def ittc(self, ranges: np.ndarray, v: float, eps: float) -> np.ndarray:
        """iTTC (s) of every ray; +inf for rays without a return."""
        gap = np.maximum(np.asarray(ranges, np.float64) - self.offset, 0.0)
        return gap / np.maximum(v * self.cos, eps)

    def points(self, ranges: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Hit points in the car frame (m); rays without a return give inf/nan."""
        r = np.asarray(ranges, np.float64)
        with np.errstate(invalid="ignore"):  # inf * 0
            return self.mount_x + r * self.cos, self.mount_y + r * self.sin

    def in_path(self, ranges: np.ndarray, margin: float, curvature: float = 0.0) -> np.ndarray:
        """True for rays whose hit point lies in the band the car's body sweeps when it keeps
        its current curvature (1/m, + left; 0: the straight-ahead box |y| <= width/2 + margin
        ahead of the front), widened by ``margin`` on each side."""
        x, y = self.points(ranges)
        ok = np.isfinite(x) & np.isfinite(y)
        hw = self.half_width + margin
        if abs(curvature) < 1e-3:
            with np.errstate(invalid="ignore"):
                return ok & (x > self.half_length - 1e-9) & (np.abs(y) <= hw)
        # kinematic single track: the car turns about a centre on its rear axle line
        radius = 1.0 / curvature
        xr = -self.rear_axle
        big = abs(radius)
        outer = np.hypot(big + self.half_width, self.half_length + self.rear_axle) + margin
        with np.errstate(invalid="ignore"):
            rho = np.hypot(x - xr, y - radius)
            ang = np.arctan2(y - radius, x - xr) - np.arctan2(-radius, -xr)
            ahead = np.mod(ang if radius > 0 else -ang, 2 * np.pi)  # angle travelled to reach it
            return ok & (rho >= big - hw) & (rho <= outer) & (ahead > 0) & (ahead < np.pi)


class BrakeLogic:
    """Debounced, hysteretic brake decision over a stream of scans.

    :param cfg: the safety section.
    :param car: car parameters.
    """

    def __init__(self, cfg: SafetyConfig, car: CarParams):
        self.cfg, self.car = cfg, car
        self._geom: dict[tuple, RayGeometry] = {}
        self.braking = False
        self.below = 0                 # consecutive scans below the threshold
        self.clear = 0                 # consecutive scans clear for release
        self.brake_t = 0.0
        self.brakes = 0
        self.false_brake_candidates = 0
        self.brake_scans = 0
        self.last_ttc = float("inf")

    def reset(self) -> None:
        """Forget the scans seen so far (not the counters): the car was moved (a new episode)."""
        self.braking = False
        self.below = self.clear = 0

    def geometry(self, angle_min: float, angle_increment: float, n: int) -> RayGeometry:
        key = (round(angle_min, 7), round(angle_increment, 9), n)
        g = self._geom.get(key)
        if g is None:
            g = self._geom[key] = RayGeometry(self.car, angle_min + angle_increment * np.arange(n))
        return g

    def scan_ttc(self, geom: RayGeometry, ranges: np.ndarray, v: float) -> tuple[float, np.ndarray]:
        """The scan's iTTC (min_rays-th smallest) and the per-ray values."""
        t = geom.ittc(ranges, v, self.cfg.eps_mps)
        k = min(self.cfg.min_rays, t.shape[0]) - 1
        return float(np.partition(t, k)[k]), t

    def update(self, geom: RayGeometry, ranges: np.ndarray, v: float, t_s: float, steer: float = 0.0) -> bool:
        """Judge one scan taken at time ``t_s`` (s) with ego speed ``v`` and front wheel angle
        ``steer`` (rad, for ``path_gate = "arc"``); True while braking."""
        c = self.cfg
        moving = v >= c.min_speed_mps
        if c.path_gate != "none":
            kappa = np.tan(steer) / geom.wheelbase if c.path_gate == "arc" else 0.0
            ranges = np.where(geom.in_path(ranges, c.lateral_margin_m, kappa), ranges, np.inf)
        ttc, per_ray = self.scan_ttc(geom, ranges, v)
        self.last_ttc = ttc
        self.below = self.below + 1 if (moving and ttc < c.threshold_s) else 0
        if self.braking:
            probe = max(v, c.release_probe_mps)
            clear = (ttc if probe == v else self.scan_ttc(geom, ranges, probe)[0]) > c.release_s
            self.clear = self.clear + 1 if clear else 0
        if not self.braking:
            if self.below >= c.debounce_scans:
                self.braking, self.brake_t, self.clear = True, t_s, 0
                self.brakes += 1
                trigger = per_ray < c.threshold_s
                if not (trigger & geom.in_path(ranges, c.lateral_margin_m)).any():
                    self.false_brake_candidates += 1
        elif self.clear >= c.release_scans and t_s - self.brake_t >= c.min_brake_s - 1e-9:
            self.braking = False
        self.brake_scans += self.braking
        return self.braking
