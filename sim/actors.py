"""Scenario actors: the obstacle cars of scenario trials, advanced by one batched model that both
world backends call (PyBullet with one world, the fast world with N), so the two agree exactly.

Each actor drives along its path (its start point, then its waypoints, then straight on) at a
speed decided by its scenario file (common/scenario.py):

- a start trigger (``[obstacles.start]``): after ``delay_s`` of sim time (exact to the substep),
  or once the ego's time to arrival at a point (distance / current speed) or its distance to the
  point falls below a value (esmini's TimeToCollisionCondition, CARLA's
  InTimeToArrivalToLocation); until then the actor stands still;
- a synchronised arrival (``[obstacles.sync]``, CARLA's SyncArrival / esmini's
  SynchronizeAction with the ego as master): each control period its speed is re-solved as
  ``v = d_actor * v_ego / d_ego`` (so it reaches its conflict point together with the ego),
  clamped to ``[speed_min, speed_max]``, until the ego is within ``release_distance_m`` or
  ``release_time_s`` of its point; then the actor holds its speed (a braking or swerving ego
  is not chased);
- speed changes along the path (``[[obstacles.speed_changes]]``): past ``at_m`` metres of its
  path the actor accelerates or brakes at ``accel`` towards ``speed`` (e.g. stops in a crossing).

Decisions (triggers, sync) are taken once per control period from the ego's state at its start;
motion is integrated per physics substep. Units SI, angles in radians.
"""

from __future__ import annotations

import math

import numpy as np

V_EGO_FLOOR = 0.05
"""m/s: the ego's speed in a time to arrival is at least this (a standing ego: far in time)."""
STRAIGHT_ON = 1000.0
"""m: the implicit path of an actor without waypoints (straight along its yaw)."""

START_TIME, START_TTA, START_DISTANCE = 0, 1, 2
START_KINDS = {"time": START_TIME, "time_to_arrival": START_TTA, "distance": START_DISTANCE}


class ActorBatch:
    """The scenario actors of N worlds, A actor slots each (unused slots stay parked).

    :param n_envs: worlds N.
    :param n_actors: actor slots A per world.
    :param max_points: path points per actor (start included).
    :param max_changes: speed changes per actor.
    """

    def __init__(self, n_envs: int, n_actors: int, max_points: int = 16, max_changes: int = 4):
        N, A, P, S = n_envs, n_actors, max_points, max_changes
        self.n_envs, self.n_actors, self.max_points, self.max_changes = N, A, P, S
        f = np.zeros
        self.used = f((N, A), bool)
        self.pts = f((N, A, P, 2))
        self.cum = np.full((N, A, P), np.inf)      # arc length at each path point
        self.n_pts = np.full((N, A), 2, np.int64)
        self.s = f((N, A))                         # arc length travelled
        self.v = f((N, A))                         # current speed (0 until started)
        self.v0 = f((N, A))                        # speed at start
        self.started = f((N, A), bool)
        self.t_start = np.full((N, A), np.inf)     # time trigger (s); inf = a condition trigger
        self.start_kind = np.full((N, A), START_TIME, np.int64)
        self.start_point = f((N, A, 2))
        self.start_value = f((N, A))
        self.sync = f((N, A), bool)
        self.released = f((N, A), bool)
        self.sync_ego_point = f((N, A, 2))
        self.sync_s = f((N, A))                    # arc length of the actor's conflict point
        self.sync_vmin, self.sync_vmax = f((N, A)), f((N, A))
        self.release_m, self.release_s = f((N, A)), f((N, A))
        self.release_still = np.full((N, A), np.inf)  # s the ego must stand still to release
        self.still_since = np.full(N, np.nan)       # time the ego stopped (nan: moving)
        self.chg_at = np.full((N, A, S), np.inf)
        self.chg_v, self.chg_acc = f((N, A, S)), f((N, A, S))
        self.v_target = np.full((N, A), np.nan)    # active speed change target (nan: none)
        self.acc = f((N, A))
        self.t = f(N)
        self.x, self.y, self.yaw = f((N, A)), f((N, A)), f((N, A))

    # ---------------------------------------------------------------------------- loading
    def load(self, env: int, obstacles) -> None:
        """Load world ``env``'s actors from a trial's obstacles (TrialObstacle list); resets
        their state and time to 0."""
        if len(obstacles) > self.n_actors:
            raise ValueError(f"obstacles: {len(obstacles)} actors, this world has {self.n_actors} slots")
        n = env
        self.used[n] = False
        self.t[n] = 0.0
        self.still_since[n] = np.nan
        for a, o in enumerate(obstacles):
            path = np.asarray(o.path, np.float64).reshape(-1, 2)
            pts = np.vstack([[o.x, o.y], path])
            if len(pts) > self.max_points:
                raise ValueError(f"obstacles.{a}.path: {len(path)} waypoints, at most {self.max_points - 1}")
            if len(pts) == 1:
                pts = np.vstack([pts, pts[0] + STRAIGHT_ON * np.array([math.cos(o.yaw), math.sin(o.yaw)])])
            seg = np.hypot(*np.diff(pts, axis=0).T)
            k = len(pts)
            self.pts[n, a] = pts[-1]
            self.pts[n, a, :k] = pts
            self.cum[n, a] = np.inf
            self.cum[n, a, :k] = np.concatenate([[0.0], np.cumsum(seg)])
            self.n_pts[n, a] = k
            self.used[n, a] = True
            self.s[n, a] = 0.0
            self.v[n, a] = 0.0
            self.v0[n, a] = o.speed
            self.started[n, a] = False
            self.released[n, a] = False
            st = o.start
            self.start_kind[n, a] = START_KINDS[st.kind]
            self.t_start[n, a] = st.value if st.kind == "time" else np.inf
            self.start_point[n, a] = st.point
            self.start_value[n, a] = st.value
            sy = o.sync
            self.sync[n, a] = sy is not None
            if sy is not None:
                self.sync_ego_point[n, a] = sy.ego_point
                self.sync_s[n, a] = project_on_path(pts, self.cum[n, a, :k], np.asarray(sy.actor_point, float))
                self.sync_vmin[n, a], self.sync_vmax[n, a] = sy.speed_min, sy.speed_max
                self.release_m[n, a], self.release_s[n, a] = sy.release_distance_m, sy.release_time_s
                self.release_still[n, a] = np.inf if sy.release_stopped_s is None else sy.release_stopped_s
            self.chg_at[n, a] = np.inf
            for j, c in enumerate(sorted(o.speed_changes, key=lambda c: c.at_m)):
                if j >= self.max_changes:
                    raise ValueError(f"obstacles.{a}.speed_changes: at most {self.max_changes}")
                self.chg_at[n, a, j], self.chg_v[n, a, j], self.chg_acc[n, a, j] = c.at_m, c.speed, c.accel
            self.v_target[n, a] = np.nan
        self._poses(np.array([n]))

    # ---------------------------------------------------------------------------- stepping
    def control(self, ego: np.ndarray) -> None:
        """Once per control period, at its start: condition triggers, synchronised speeds and
        releases from the ego's state.

        :param ego: (N, 4) ego x, y, yaw, forward speed v.
        """
        ego = np.asarray(ego, np.float64).reshape(self.n_envs, -1)
        ex, ey, ev = ego[:, 0:1], ego[:, 1:2], np.maximum(ego[:, 3:4], V_EGO_FLOOR)
        # condition start triggers (time triggers are exact, in advance())
        d_trig = np.hypot(self.start_point[..., 0] - ex, self.start_point[..., 1] - ey)
        cond = np.where(self.start_kind == START_TTA, d_trig / ev, d_trig)
        fire = self.used & ~self.started & (self.start_kind != START_TIME) & (cond <= self.start_value)
        self.started |= fire
        self.v = np.where(fire, self.v0, self.v)
        # the ego standing still: since when (a yielding ego releases actors that set release_stopped_s)
        still = ego[:, 3] < V_EGO_FLOOR
        self.still_since = np.where(still, np.where(np.isnan(self.still_since), self.t, self.still_since), np.nan)
        # synchronised arrival: re-solve, or release
        live = self.used & self.started & self.sync & ~self.released
        if live.any():
            waited = live & ((self.t - self.still_since)[:, None] >= self.release_still)  # nan: False
            self.released |= waited
            self.v = np.where(waited, self.v0, self.v)
            live &= ~waited
            d_e = np.hypot(self.sync_ego_point[..., 0] - ex, self.sync_ego_point[..., 1] - ey)
            tta = d_e / ev
            d_a = self.sync_s - self.s
            release = live & ((d_e <= self.release_m) | (tta <= self.release_s) | (d_a <= 0.0))
            self.released |= release
            solve = live & ~release
            v_req = np.clip(d_a / np.maximum(tta, 1e-6), self.sync_vmin, self.sync_vmax)
            self.v = np.where(solve, v_req, self.v)

    def advance(self, dt: float) -> None:
        """One physics substep of ``dt`` seconds: time triggers, speed changes, motion, poses."""
        t0 = self.t[:, None]
        t1 = t0 + dt
        # time triggers start at their exact time inside the substep
        fire = self.used & ~self.started & (self.t_start < t1 + 1e-12)
        moving_dt = np.where(fire, t1 - np.maximum(t0, self.t_start), dt)
        self.started |= fire
        self.v = np.where(fire, self.v0, self.v)
        # speed changes: the latest change passed along the path sets the target
        passed = self.s[..., None] >= self.chg_at
        has = passed.any(-1)
        if has.any():
            last = np.where(passed, np.arange(self.max_changes), -1).max(-1)
            idx = np.maximum(last, 0)[..., None]
            tgt = np.take_along_axis(self.chg_v, idx, -1)[..., 0]
            acc = np.take_along_axis(self.chg_acc, idx, -1)[..., 0]
            sel = has & self.started
            dv = np.clip(tgt - self.v, -acc * dt, acc * dt)
            self.v = np.where(sel, self.v + dv, self.v)
            self.released |= sel  # a scripted speed change ends any synchronisation
        self.s = np.where(self.started, self.s + self.v * np.maximum(moving_dt, 0.0), self.s)
        self.t += dt
        self._poses(slice(None))  # views, not copies: this runs every physics substep

    def _poses(self, envs) -> None:
        """Pose at arc length s on each actor's polyline (straight on past its end); ``envs``: an
        index array or a slice."""
        s = self.s[envs]
        cum = self.cum[envs]
        k = np.clip((cum <= s[..., None]).sum(-1) - 1, 0, self.n_pts[envs] - 2)
        a = np.take_along_axis(self.pts[envs], k[..., None, None].repeat(2, -1), 2)[..., 0, :]
        b = np.take_along_axis(self.pts[envs], (k + 1)[..., None, None].repeat(2, -1), 2)[..., 0, :]
        c0 = np.take_along_axis(cum, k[..., None], -1)[..., 0]
        d = b - a
        seg = np.hypot(d[..., 0], d[..., 1])
        with np.errstate(invalid="ignore"):  # parked slots (no path) are overwritten below
            u = (s - c0) / np.maximum(seg, 1e-12)
            p = a + d * u[..., None]
        parked = ~self.used[envs]  # unused slots: far away, neither seen nor touched
        self.x[envs] = np.where(parked, 1e6 + 10.0 * np.arange(self.n_actors), p[..., 0])
        self.y[envs] = np.where(parked, 1e6, p[..., 1])
        self.yaw[envs] = np.arctan2(d[..., 1], d[..., 0])

    def speeds(self) -> np.ndarray:
        """(N, A) current speeds (m/s)."""
        return self.v.copy()


def project_on_path(pts: np.ndarray, cum: np.ndarray, q: np.ndarray) -> float:
    """Arc length of the point of polyline ``pts`` closest to ``q`` (the path's last segment
    extended straight on)."""
    best, best_d = 0.0, math.inf
    for i in range(len(pts) - 1):
        a, b = pts[i], pts[i + 1]
        d = b - a
        seg2 = float(d @ d)
        u = float((q - a) @ d / max(seg2, 1e-12))
        u = max(u, 0.0) if i == len(pts) - 2 else min(max(u, 0.0), 1.0)
        dist = float(np.hypot(*(a + d * u - q)))
        if dist < best_d:
            best, best_d = cum[i] + u * math.sqrt(seg2), dist
    return best
