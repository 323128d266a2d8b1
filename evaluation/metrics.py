"""Per-trial metrics computed from the recorded ground truth (numpy, vectorised over time)."""

from __future__ import annotations

import numpy as np


def box_corners(x, y, yaw, length, width) -> np.ndarray:
    """Corners (T, 4, 2) of oriented rectangles centred at (x, y), counter-clockwise."""
    x, y, yaw = (np.asarray(v, np.float64) for v in (x, y, yaw))
    length, width = np.broadcast_to(length, x.shape), np.broadcast_to(width, x.shape)
    c, s = np.cos(yaw), np.sin(yaw)
    hx, hy = length / 2, width / 2
    local = np.array([[1, -1], [1, 1], [-1, 1], [-1, -1]], np.float64)  # (4, 2) signs
    lx, ly = local[None, :, 0] * hx[:, None], local[None, :, 1] * hy[:, None]
    return np.stack([x[:, None] + c[:, None] * lx - s[:, None] * ly,
                     y[:, None] + s[:, None] * lx + c[:, None] * ly], -1)


def _point_segment(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distances (T, P, S) from points p (T, P, 2) to segments a->b (T, S, 2)."""
    d = (b - a)[:, None, :, :]
    ap = p[:, :, None, :] - a[:, None, :, :]
    t = np.clip((ap * d).sum(-1) / np.maximum((d * d).sum(-1), 1e-12), 0.0, 1.0)
    return np.linalg.norm(ap - d * t[..., None], axis=-1)


def _overlap(ca: np.ndarray, cb: np.ndarray) -> np.ndarray:
    """Separating-axis test of two convex quads per row: (T,) bool, True = they intersect."""
    sep = np.zeros(ca.shape[0], bool)
    for poly in (ca, cb):
        for k in range(2):  # a rectangle has two distinct edge normals
            e = poly[:, k + 1] - poly[:, k]
            n = np.stack([-e[:, 1], e[:, 0]], -1)
            pa, pb = (ca * n[:, None]).sum(-1), (cb * n[:, None]).sum(-1)
            sep |= (pa.max(1) < pb.min(1)) | (pb.max(1) < pa.min(1))
    return ~sep


def footprint_gap(ca: np.ndarray, cb: np.ndarray) -> np.ndarray:
    """Distance (T,) between two rectangles per row given their corners (T, 4, 2); 0 if touching."""
    ea, eb = np.roll(ca, -1, axis=1), np.roll(cb, -1, axis=1)
    d = np.minimum(_point_segment(ca, cb, eb).min((1, 2)), _point_segment(cb, ca, ea).min((1, 2)))
    return np.where(_overlap(ca, cb), 0.0, d)


# ---------------------------------------------------------------------------- per-trial measures
# The benchmark's definitions (docs/results.md, "Per-trial measures"); changing one changes what
# every stored cell means, so they are constants here, not configuration.
STANDING_SPEED = 0.05
"""m/s: below this the ego is standing."""
FROZEN_AFTER_S = 2.0
"""Standing longer than this while its path is free is frozen."""
PATH_LOOKAHEAD_M = 1.5
"""The ego's path: a corridor this long ahead of its front bumper ..."""
PATH_MARGIN_M = 0.1
"""... and its width plus this on either side."""
PATH_HORIZON_S = 1.0
"""The path is free at t when no other car's footprint touches the corridor from t to t + this
(ground truth in hindsight: a car about to cross is not a free path)."""
DRIVE_OFF_SPEED = 0.2
"""m/s: a trial from rest has driven off once its speed first reaches this."""
FROUDE_SPEED = 0.1 ** 0.5
"""Speeds scale with sqrt(length) at equal Froude number: 1/10 scale -> x0.316."""
IMPACT_BANDS_MPS = tuple(round(k / 3.6 * FROUDE_SPEED, 2) for k in (5, 15, 30, 40))
"""Upper impact speeds (m/s) of the Euro NCAP AEB car-to-car scoring bands (impact below 5 / 15 /
30 / 40 km/h scores 1 / 0.75 / 0.5 / 0.25, above: 0), Froude-scaled: 0.44 / 1.32 / 2.64 / 3.51."""
BAND_SCORES = (1.0, 0.75, 0.5, 0.25, 0.0)
CARLA_PENALTY = {"vehicle": 0.6, "static": 0.65, "timeout": 0.7}
"""CARLA Leaderboard 2.0 infraction multipliers (statistics_manager.py): collision with a vehicle,
with a static object (here: walls, the ground, a rollover), scenario timeout (here: the duration
ended short of the route)."""


def impact_band(speed: float) -> int:
    """Index of the Euro NCAP band of an impact speed (0: below 0.44 m/s ... 4: 3.51 m/s and above)."""
    return sum(speed >= b for b in IMPACT_BANDS_MPS)


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """(first, last) index of every run of True in a 1-D bool array."""
    d = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1) - 1))


def path_free(t: np.ndarray, ego: np.ndarray, car: tuple[float, float], obstacles: list[np.ndarray],
              sizes: list[tuple[float, float]]) -> np.ndarray:
    """(T,) bool: no obstacle car touches the corridor ahead of the ego (PATH_LOOKAHEAD_M long, its
    width + 2 PATH_MARGIN_M, from its front bumper, at its pose of step i) at any step from i to
    i + PATH_HORIZON_S.

    :param ego: (T, 3) x, y, yaw. :param obstacles: per car (T, >=3) x, y, yaw[, speed].
    """
    T = len(t)
    free = np.ones(T, bool)
    if T == 0 or not obstacles:
        return free
    length, width = car
    c, s = np.cos(ego[:, 2]), np.sin(ego[:, 2])
    ahead = length / 2 + PATH_LOOKAHEAD_M / 2
    corridor = box_corners(ego[:, 0] + c * ahead, ego[:, 1] + s * ahead, ego[:, 2], PATH_LOOKAHEAD_M,
                           width + 2 * PATH_MARGIN_M)
    dt = float(np.median(np.diff(t))) if T > 1 else 1.0
    horizon = int(round(PATH_HORIZON_S / max(dt, 1e-9)))
    for tr, (ol, ow) in zip(obstacles, sizes):
        box = box_corners(tr[:, 0], tr[:, 1], tr[:, 2], ol, ow)
        for k in range(min(horizon, T - 1) + 1):  # the car k steps later against the corridor now
            free[:T - k] &= ~_overlap(corridor[:T - k], box[k:])
    return free


def trial_measures(t, ego, ego_velocity, obstacles, sizes, car, collided: bool, contact_with: str,
                   progress_m: float, route_m: float, success: bool):
    """The benchmark's per-trial measures (results.Measures) from the recorded ground truth.

    :param t: (T,) trial time. :param ego: (T, 3) x, y, yaw. :param ego_velocity: (T, 2) world-frame
        velocity. :param obstacles: per obstacle car (T, 4) x, y, yaw, speed (along its yaw), in the
        order of the sim's ids (car<k> is obstacle k - 1). :param sizes: their (length, width).
    :param car: the ego's (length, width). :param route_m: the scenario's min_progress_m.
    """
    from racecav.evaluation.results import Measures

    t, ego, vel = np.asarray(t, float), np.asarray(ego, float), np.asarray(ego_velocity, float)
    speed = np.hypot(vel[:, 0], vel[:, 1])
    # impact speed: relative to what was hit, at the last step before contact
    impact = band = None
    if collided:
        k = max(len(t) - 2, 0)
        other = np.zeros(2)
        if contact_with.startswith("car") and contact_with[3:].isdigit():
            j = int(contact_with[3:]) - 1
            if 0 <= j < len(obstacles):
                x, y, yaw, v = obstacles[j][k][:4]
                other = v * np.array([np.cos(yaw), np.sin(yaw)])
        impact = float(np.hypot(*(vel[k] - other)))
        band = impact_band(impact)
    # frozen: standing > FROZEN_AFTER_S with the path free, or the time ran out short of the route
    idle = (speed < STANDING_SPEED) & path_free(t, ego, car, list(obstacles), list(sizes))
    longest = max((float(t[b] - t[a]) for a, b in _runs(idle)), default=0.0)
    timeout = not collided and not success
    standing = longest > FROZEN_AFTER_S
    # drive-off from rest
    from_rest = bool(len(speed) and speed[0] < STANDING_SPEED)
    moving = np.flatnonzero(speed >= DRIVE_OFF_SPEED)
    drive_off = float(t[moving[0]]) if from_rest and moving.size else None
    # CARLA driving score: route completion x the infraction's multiplier
    completion = 1.0 if route_m <= 0 else float(np.clip(progress_m / route_m, 0.0, 1.0))
    infraction = ""
    if collided:
        infraction = "vehicle" if contact_with.startswith("car") else "static"
    elif timeout:
        infraction = "timeout"
    score = completion * CARLA_PENALTY.get(infraction, 1.0)
    return Measures(impact_speed_mps=None if impact is None else round(impact, 4), impact_band=band,
                    frozen=standing or timeout, frozen_reason="standing" if standing else "short" if timeout else "",
                    longest_free_standing_s=round(longest, 4), from_rest=from_rest,
                    drive_off_s=None if drive_off is None else round(drive_off, 4),
                    route_completion=round(completion, 4), infraction=infraction, driving_score=round(score, 4))
