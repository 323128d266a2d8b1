"""A teacher that knows no family: predict every car, try a few manoeuvres, take the first clear one.

Every control step it reads the fast world's privileged state (training only; the policy it
teaches sees only its scans):

- the pose, speed, path and scripted speed changes (sim/actors.py) of every scenario actor that the
  ego's lidar has returned from in the last SEEN_MEMORY_S (a label for a car the policy cannot see
  is one it cannot learn), predicted HORIZON_S ahead along its path at its current speed, the
  speed changes applied. An actor that has not started stays where it is: no driver can know
  when a parked car will pull out;
- the ego's road (the straight road or way of the scenario's world that the ego starts on, its
  width; :func:`ego_road`), predicted under each manoeuvre of a small set: on at full throttle,
  at 1.6 / 0.9 / 0.4 m/s, stop, in its lane; or a shift to either side (SHIFTS_M, wider where the
  road allows) at full throttle or 0.9 m/s.

It takes the first manoeuvre, in a preference order, whose predicted footprint (two circles per
car) keeps MARGIN_M from every actor's over the horizon:

- on at full throttle whenever that is clear: on a free road it drives off at once, and a stop
  ends as soon as going on is clear;
- else, for the car the full-throttle plan meets first: a crossing car (or one ahead going the
  ego's way faster than CRAWL_V): slow down or yield first, steer round second; a car standing in
  the way, coming at the ego along its road, or crawling ahead slower than CRAWL_V: steer round
  first;
- when none is clear, the one whose first contact comes latest (then the widest clearance).

The steering label is a pure pursuit (LOOKAHEAD_M, longer at speed) of the chosen manoeuvre's predicted path, not
of its final offset (which steers back into a car standing beside the ego). Labels are in the
shipped avoid's action space: throttle, the brake below ``BRAKE_BELOW``, steering.

``python -m racecav.training.predictive_teacher --suite roads --splits test,ood,controls`` drives
it by its own labels in the fast world, per family and split, beside both non-evading references
on the same seeds (docs/teacher.md).
"""

from __future__ import annotations

import argparse
import math
import sys
from dataclasses import dataclass
from types import SimpleNamespace
from pathlib import Path

import numba
import numpy as np

from racecav.common.vehicle import brake_from_action, throttle_for_speed, wheel_speed_step

HORIZON_S = 2.5     # s of prediction
DT = 0.1            # s between predicted poses
MARGIN_M = 0.12     # m kept between predicted footprints (circles)
SPEEDS = (1.6, 0.9, 0.4)  # m/s of the slow-down manoeuvres, in their order
SHIFTS_M = (0.45, 0.7, 0.95, math.inf)  # m to either side, clipped to the road (inf: as far as
                                         # it allows); the first that is clear wins: the smallest
DODGE_SPEEDS = (None, 0.9)  # a shift at full throttle, then at 0.9 m/s
CURB_M = 0.1        # m the ego's side keeps from the curb in a shift
CRAWL_V = 0.9       # m/s: a car ahead going the ego's way slower than this is passed, not followed
STILL_V = 0.05      # m/s: a car slower than this stands
WAIT_RANGE_M = 8.0  # m ahead along the ego's road in which a crawling crossing car is waited for
SEEN_MEMORY_S = 0.5  # s an actor counts as seen after the ego's lidar last returned from it (the
                     # policy's memory: its stacked scans span 0.4 s)
STOP_MIN_S = 1.2    # s a stop lasts at least: a driver who stops, stands (and a car that waits
                    # for the ego goes once it has stood a while)
ALONG_SIN = 0.5     # |sin| of a car's heading off the ego's road below which it drives along it
LOOKAHEAD_M = 0.9   # m of pure pursuit along the chosen path ...
LOOKAHEAD_S = 0.6   # ... or this many seconds of the ego's speed, if longer (no weave at speed)
PATH_DS = 0.1       # m between points of a manoeuvre's path
SPEED_SUBSTEPS = 2  # Euler steps per DT of the predicted wheel speed
HEADING_MAX = (0.45, 0.8)  # rad, the largest heading off the road in a shift at full throttle, slower
HEADING_SLOW_V = 1.0  # m/s: a manoeuvre up to this speed may take the larger heading
LATERAL_GAIN = 1.2  # rad of heading per m of lateral error
CURVATURE_MAX = 0.7  # 1/m the predicted path turns at most (the car's 0.8, less for the servo's lag)
SLACK_V = 0.15      # m/s above a manoeuvre's speed before its label brakes
BRAKE_BELOW = -0.5  # the shipped avoid's brake (EnvConfig.brake_below)
VIEW = "wide"       # the shipped avoid's lidar view (training/recipes/avoid.toml, EnvConfig.lidar):
                    # the probe's world scans with it, so the teacher sees what its student sees.
                    # With the car's default (the paper's frontal +-45 deg) a car crossing from
                    # the side at a bearing of 50-60 deg stayed unseen until contact: the probe
                    # measured a teacher blinder than the one the student imitates
SELECTION_SEED = 1000  # the probe's seeds; the table's test trials use seeds from 0


@dataclass(frozen=True)
class Road:
    """The ego's road: a point on its centre line, its heading (the ego's direction), its width
    and the lateral offset (m, left positive) of the ego's lane centre."""

    x: float
    y: float
    yaw: float
    width: float
    lane: float


def _straights(f) -> list[tuple[float, float, float, float, float]]:
    """(cx, cy, yaw, length, width) of a world file's straight roads and of every way's first
    straight piece (the ego starts on a straight)."""
    out = [(r.cx, r.cy, math.radians(r.yaw_deg), r.length, r.width) for r in f.roads]
    for w in f.ways:
        p = w.pieces[0]
        if p.straight is not None:
            h = math.radians(w.yaw_deg)
            out.append((w.x + 0.5 * p.straight * math.cos(h), w.y + 0.5 * p.straight * math.sin(h), h,
                        p.straight, w.width))
    return out


def ego_road(sc, x: float, y: float, yaw: float, world=None) -> Road:
    """The road the ego starts on at (x, y, yaw): among the scenario world's straight roads (and
    ways' first straights) the one that holds the point and runs within 30 deg of the heading,
    the narrowest if several do (the junction's other road is wider there). A world without
    roads (a loop) or an ego on none: a road along the start heading, the world's lane width."""
    from racecav.common.vehicle import load_toml
    from racecav.common.world import WORLDS_DIR, WorldFile

    f = sc.map
    if f is None and sc.world is not None:
        try:
            f = load_toml(sc.world, WORLDS_DIR, WorldFile, "world")
        except ValueError:
            f = None
    best = None
    for cx, cy, h, length, width in (_straights(f) if f is not None and f.kind == "roads" else []):
        c, s = math.cos(h), math.sin(h)
        along, lat = (x - cx) * c + (y - cy) * s, -(x - cx) * s + (y - cy) * c
        if abs(along) > length / 2 or abs(lat) > width / 2 or abs(math.sin(yaw - h)) > ALONG_SIN:
            continue
        if math.cos(yaw - h) < 0:  # the road's heading the ego's way
            h, lat = h + math.pi, -lat
        if best is None or width < best.width:
            best = Road(cx, cy, math.atan2(math.sin(h), math.cos(h)), width, lat)
    if best is None:
        width = float(world.lane_width) if world is not None else 2.0
        best = Road(x, y, yaw, width, 0.0)
    return best


def path_poses(pts: np.ndarray, cum: np.ndarray, n_pts: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, ...]:
    """x, y, yaw at arc lengths ``s`` (N, A, T) on the actors' polylines ``pts`` (N, A, P, 2) with
    arc lengths ``cum`` (N, A, P) and ``n_pts`` (N, A) points (straight on past the last): the
    same rule as ActorBatch._poses, for many times at once."""
    k = np.clip((cum[:, :, None, :] <= s[..., None]).sum(-1) - 1, 0, n_pts[:, :, None] - 2)
    a = np.take_along_axis(pts, k[..., None].repeat(2, -1), 2)
    b = np.take_along_axis(pts, (k + 1)[..., None].repeat(2, -1), 2)
    c0 = np.take_along_axis(cum, k, 2)
    d = b - a
    seg = np.maximum(np.hypot(d[..., 0], d[..., 1]), 1e-12)
    with np.errstate(invalid="ignore"):  # unused slots (no path): replaced by the caller
        p = a + d * ((s - c0) / seg)[..., None]
    return p[..., 0], p[..., 1], np.arctan2(d[..., 1], d[..., 0])


def predict_actors(acts, steps: int, dt: float = DT, nominal: bool = False) -> tuple[np.ndarray, ...]:
    """x, y, yaw, speed (N, A, steps + 1) of every actor now and every ``dt`` after: along its path at
    its current speed, its scripted speed changes applied (as ActorBatch.advance); an actor not
    started stays put. ``nominal``: a synchronised actor not yet released at its nominal speed
    instead (the speed it goes on at once it stops waiting for the ego)."""
    s, v = acts.s.copy(), acts.v.copy()
    if nominal:
        v = np.where(acts.sync & ~acts.released & acts.started, acts.v0, v)
    go = acts.used & acts.started
    out, speeds = [s.copy()], [v * go]
    for _ in range(steps):
        passed = s[..., None] >= acts.chg_at
        has = passed.any(-1) & go
        if has.any():
            idx = np.maximum(np.where(passed, np.arange(acts.max_changes), -1).max(-1), 0)[..., None]
            tgt = np.take_along_axis(acts.chg_v, idx, -1)[..., 0]
            acc = np.take_along_axis(acts.chg_acc, idx, -1)[..., 0]
            v = np.where(has, v + np.clip(tgt - v, -acc * dt, acc * dt), v)
        s = np.where(go, s + v * dt, s)
        out.append(s.copy())
        speeds.append(v * go)
    x, y, yaw = path_poses(acts.pts, acts.cum, acts.n_pts, np.stack(out, -1))
    used = acts.used[..., None]
    return np.where(used, x, 1e6), np.where(used, y, 1e6), yaw, np.stack(speeds, -1)


ACTOR_FIELDS = {  # ActorBatch arrays the prediction reads, and the value of an unused slot
    "used": False, "pts": 0.0, "cum": np.inf, "n_pts": 2, "s": 0.0, "v": 0.0, "v0": 0.0, "started": False,
    "sync": False, "released": False, "chg_at": np.inf, "chg_v": 0.0, "chg_acc": 0.0, "yaw": 0.0,
    "x": 1e6, "y": 1e6}


class Batch:
    """One or several FastWorlds seen by the teacher as one batch (the fast VecEnv's scenario
    worlds, one per map): the egos' state and every actor, padded to the largest actor count,
    path length and speed-change table. One batch, one pass of the prediction: its cost is in
    its Python loops over time steps and path points, not in the number of worlds."""

    def __init__(self, worlds):
        worlds = list(worlds)
        if not worlds or any(w.actors is None for w in worlds):
            raise ValueError("the predictive teacher needs scenario worlds (their actors' paths)")
        first = worlds[0]
        for w in worlds[1:]:
            if (w.car is not first.car and w.car != first.car) or w.agent_speed_scale != first.agent_speed_scale:
                raise ValueError("the predictive teacher's worlds must share the car and its speed scale")
        self.worlds = worlds
        self.car, self.agent_speed_scale, self.brake_decel = first.car, first.agent_speed_scale, first.brake_decel
        self.n_envs = sum(w.n_envs for w in worlds)
        self.owner = [(w, n) for w in worlds for n in range(w.n_envs)]  # env -> (world, its index there)
        self.refresh()

    def refresh(self) -> None:
        """Read the worlds' current state (an episode reset loads new paths: every call)."""
        ws = self.worlds
        for k in ("x", "y", "yaw", "v", "w"):
            setattr(self, k, np.concatenate([getattr(w, k)[:, 0] for w in ws]))
        self.time = np.concatenate([w.time for w in ws])
        acts = [w.actors for w in ws]
        A = max(1, max(a.n_actors for a in acts))
        P = max(a.max_points for a in acts)
        S = max(a.max_changes for a in acts)
        out = SimpleNamespace(n_actors=A, max_changes=S)
        for k, fill in ACTOR_FIELDS.items():
            ref = getattr(acts[0], k)
            tail = (P,) if k in ("pts", "cum") else (S,) if k.startswith("chg_") else ()
            arr = np.full((self.n_envs, A, *tail, *ref.shape[3:]), fill, ref.dtype)
            i = 0
            for a in acts:
                src = getattr(a, k)
                arr[(slice(i, i + a.n_envs), *(slice(0, d) for d in src.shape[1:]))] = src
                i += a.n_envs
            setattr(out, k, arr)
        self.actors = out

    def seen(self) -> np.ndarray:
        """(N, A) the actors that return at least one ray of the ego's scan now (line of sight past
        walls and cars, in the view and range of the policy's lidar; FastWorld.seen_by_agent, from
        the current pose: the world's last scan may be older)."""
        out = np.zeros(self.actors.used.shape, bool)
        i = 0
        for w in self.worlds:
            envs = np.arange(w.n_envs)
            pose = np.stack([w.x[:, 0], w.y[:, 0], w.yaw[:, 0]], 1)
            s = w.seen_by_agent(envs, pose=pose)
            out[i:i + w.n_envs, :s.shape[1]] = s
            i += w.n_envs
        return out

    def ego_road(self, n: int) -> Road:
        w, i = self.owner[n]
        sc = w.scenarios[int(w.scenario_index[i])]
        return ego_road(sc, *w.start_pose[i], world=w.world)

    def road_key(self, n: int) -> tuple:
        w, i = self.owner[n]
        return id(w), int(w.scenario_index[i]), tuple(np.round(w.start_pose[i], 3))


@numba.njit(cache=True)
def _clearance(gx, gy, gyaw, ax, ay, ayaw, used, off, radii):
    """(N, M, A, T): per manoeuvre, actor and time, the least distance between the ego's two
    circles and the actor's two, minus ``radii`` (the batch's largest array: a loop, not numpy)."""
    N, M, T = gx.shape
    A = ax.shape[1]
    out = np.full((N, M, A, T), np.inf)
    for n in range(N):
        for a in range(A):
            if not used[n, a]:
                continue
            for t in range(T):
                c, s = math.cos(ayaw[n, a, t]), math.sin(ayaw[n, a, t])
                a1x, a1y = ax[n, a, t] - off * c, ay[n, a, t] - off * s
                a2x, a2y = ax[n, a, t] + off * c, ay[n, a, t] + off * s
                for m in range(M):
                    ec, es = math.cos(gyaw[n, m, t]), math.sin(gyaw[n, m, t])
                    best = np.inf
                    for sg in (-1.0, 1.0):
                        ex, ey = gx[n, m, t] + sg * off * ec, gy[n, m, t] + sg * off * es
                        d1 = (ex - a1x) ** 2 + (ey - a1y) ** 2
                        d2 = (ex - a2x) ** 2 + (ey - a2y) ** 2
                        best = min(best, d1, d2)
                    out[n, m, a, t] = math.sqrt(best) - radii
    return out


class PredictiveTeacher:
    """Labels for every env of one scenario FastWorld or of several (read, never changed).

    :param worlds: a FastWorld with scenarios (``world.actors``), or a list of them (labels in
        their order, concatenated).
    :param horizon_s: prediction horizon (s).
    :param margin_m: clearance kept between the predicted footprints (m).
    """

    def __init__(self, worlds, horizon_s: float = HORIZON_S, margin_m: float = MARGIN_M):
        self.w = Batch(worlds if isinstance(worlds, (list, tuple)) else [worlds])
        self.car = car = self.w.car
        self.steps = int(round(horizon_s / DT))
        self.margin = margin_m
        self.v_full = car.v_max * self.w.agent_speed_scale
        # the footprint: two circles on the car's axis, a quarter length either side of its centre
        self.c_off = car.length / 4
        self.c_r = math.hypot(car.length / 4, car.width / 2)
        self._roads: dict[tuple, Road] = {}
        self.choice = np.zeros(self.w.n_envs, np.int64)
        """(N,) the manoeuvre each env's last label follows (an index into ``names``)."""
        self.stop_at = np.full(self.w.n_envs, np.inf)
        """(N,) the time each env's current stop began (inf: not stopped)."""
        self.seen_at = np.full((self.w.n_envs, self.w.actors.n_actors), -np.inf)
        """(N, A) when the ego's lidar last returned from each actor (-inf: not in this episode)."""
        self.last_time = np.zeros(self.w.n_envs)
        self.names: list[str] = []

    def road(self, n: int) -> Road:
        """Env ``n``'s ego road (per world, scenario and start; cached)."""
        key = self.w.road_key(n)
        if key not in self._roads:
            self._roads[key] = self.w.ego_road(n)
        return self._roads[key]

    def steered(self) -> np.ndarray:
        """(N,) the last labels steer round a car (a shift manoeuvre)."""
        return np.array(["@" in self.names[c] for c in self.choice]) if self.names else np.zeros(len(self.choice), bool)

    # ------------------------------------------------------------------ manoeuvres
    def manoeuvres(self, roads: list[Road]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(speed (M,), lateral target (N, M), shift (M,) bool) of the manoeuvres: in the lane at
        full throttle (inf), each of SPEEDS, stop (0); then each shift to the left and to the
        right at each of DODGE_SPEEDS, clipped to the road (so on a narrow road the far side's
        shifts are wider than the near side's)."""
        lane = np.array([r.lane for r in roads])
        room = np.array([r.width / 2 - self.car.width / 2 - CURB_M for r in roads])
        speeds, lat, names = [np.inf, *SPEEDS, 0.0], [lane] * (len(SPEEDS) + 2), ["full", *map(str, SPEEDS), "stop"]
        for v in DODGE_SPEEDS:
            for side, tag in ((1.0, "left"), (-1.0, "right")):
                for d in SHIFTS_M:
                    speeds.append(np.inf if v is None else v)
                    lat.append(np.clip(lane + side * d, -room, room))
                    names.append(f"{tag} {'max' if np.isinf(d) else d} @{'full' if v is None else v}")
        self.names = names
        return np.array(speeds), np.stack(lat, 1), np.array(["@" in n for n in names])

    def _paths(self, l0, psi0, lat_t, n_pts: int, psi_max: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Each manoeuvre's path (N, M, n_pts) in the road frame from the ego: along (from 0),
        lateral, heading off the road; every PATH_DS of arc: the heading turns towards the lateral
        target at most CURVATURE_MAX per metre and at most ``psi_max`` (M,) off the road."""
        N, M = lat_t.shape
        s, l, psi = np.zeros((N, M)), np.broadcast_to(l0[:, None], (N, M)).copy(), np.broadcast_to(psi0[:, None], (N, M)).copy()
        S, L, P = [s], [l], [psi]
        turn = CURVATURE_MAX * PATH_DS
        for _ in range(n_pts - 1):
            want = np.clip(LATERAL_GAIN * (lat_t - l), -psi_max, psi_max)
            psi = psi + np.clip(want - psi, -turn, turn)
            s = s + PATH_DS * np.cos(psi)
            l = l + PATH_DS * np.sin(psi)
            S.append(s)
            L.append(l)
            P.append(psi)
        return np.stack(S, -1), np.stack(L, -1), np.stack(P, -1)

    def _speeds(self, v0: np.ndarray, w0: np.ndarray, speed: np.ndarray) -> np.ndarray:
        """(N, M, steps + 1) distance driven under each manoeuvre's throttle or brake label (the
        friction model of the wheels; the brake at the car's braking deceleration)."""
        car, w = self.car, self.w
        scale = car.wheel_radius * w.agent_speed_scale
        thr = np.where(np.isinf(speed), 1.0, throttle_for_speed(np.where(np.isinf(speed), 0.0, speed), car, w.agent_speed_scale))
        N, M = len(v0), len(speed)
        v = np.broadcast_to(v0[:, None], (N, M)).copy()
        wh = np.broadcast_to(w0[:, None], (N, M)).copy()
        d = np.zeros((N, M))
        out = [d]
        sub = SPEED_SUBSTEPS
        dt = DT / sub
        for _ in range(self.steps):
            for _k in range(sub):
                brake = v > speed + SLACK_V
                wh = np.where(brake, np.maximum(v - w.brake_decel * dt, 0.0) / scale,
                              wheel_speed_step(wh, thr[None, :], dt, car))
                v_new = wh * scale
                d = d + 0.5 * (v + v_new) * dt
                v = v_new
            out.append(d)
        return np.stack(out, -1)

    # ------------------------------------------------------------------ labels
    def labels(self) -> np.ndarray:
        """(N, 2) a_T, a_delta for every world's current state."""
        w, car = self.w, self.car
        w.refresh()
        w.actors.used = w.actors.used & self._seen()
        N = w.n_envs
        roads = [self.road(n) for n in range(N)]
        rx, ry, ryaw = (np.array([getattr(r, k) for r in roads]) for k in ("x", "y", "yaw"))
        c, s = np.cos(ryaw), np.sin(ryaw)
        ex, ey, eyaw, ev = w.x, w.y, w.yaw, w.v
        e_s = (ex - rx) * c + (ey - ry) * s
        e_l = -(ex - rx) * s + (ey - ry) * c
        psi0 = np.angle(np.exp(1j * (eyaw - ryaw)))
        speed, lat_t, shift = self.manoeuvres(roads)
        M = len(speed)
        # the ego: distance driven over time under each manoeuvre, its path by distance
        dist = self._speeds(ev, w.w, speed)  # (N, M, T)
        look = np.maximum(LOOKAHEAD_M, LOOKAHEAD_S * ev)
        n_pts = int(math.ceil(max(dist.max(), look.max()) / PATH_DS)) + 2
        psi_max = np.where(speed <= HEADING_SLOW_V, HEADING_MAX[1], HEADING_MAX[0])
        ps, pl, pp = self._paths(e_l, psi0, lat_t, n_pts, psi_max)
        k = np.clip(dist / PATH_DS, 0, n_pts - 1.001)
        i0 = k.astype(np.int64)
        f = k - i0

        def at(a):
            return np.take_along_axis(a, i0, 2) * (1 - f) + np.take_along_axis(a, i0 + 1, 2) * f

        gs, gl, gp = at(ps) + e_s[:, None, None], at(pl), at(pp)
        gx = rx[:, None, None] + gs * c[:, None, None] - gl * s[:, None, None]
        gy = ry[:, None, None] + gs * s[:, None, None] + gl * c[:, None, None]
        gyaw = ryaw[:, None, None] + gp
        # the actors
        # the actors, twice: at their speeds, and a car that has slowed for the ego at its own speed
        # again (it may go on any time: a yield ends when it has passed, not when it crawls)
        A = w.actors.n_actors
        ax, ay, ayaw, av = (np.concatenate(z, 1) for z in zip(predict_actors(w.actors, self.steps),
                                                          predict_actors(w.actors, self.steps, nominal=True)))
        clear = self._clearance(gx, gy, gyaw, ax, ay, ayaw)  # (N, M, A, T)
        hit = clear < self.margin
        ok = ~hit.any((2, 3))  # (N, M)
        touch_free = (clear > 0).all((2, 3))
        # the order: which car does the full-throttle plan meet first, and is it one to steer round?
        first_t = np.where(hit[:, 0].any(-1), hit[:, 0].argmax(-1), 10**6)  # (N, A)
        who = first_t.argmin(-1)
        t_meet = np.minimum(first_t[np.arange(N), who], self.steps)
        v_meet = av[np.arange(N), who, t_meet]  # its predicted speed when they would meet
        steer_first, standing, waiting = self._steer_first(who % A, ryaw, v_meet)
        stop = len(SPEEDS) + 1
        order_slow = [0, *range(1, len(SPEEDS) + 2), *np.flatnonzero(shift)]
        order_steer = [0, *np.flatnonzero(shift), *range(1, len(SPEEDS) + 2)]
        # a crossing car crawling towards the conflict: it waits for the ego (or is about to go);
        # creeping on keeps it waiting, so stop and let it through
        order_wait = [0, stop, *np.flatnonzero(shift)]
        # fallback: the manoeuvre whose first contact comes latest, then the widest clearance
        t_hit = np.where(hit.any(2).any(-1), hit.any(2).argmax(-1), 10**6)
        worst = np.where(np.isfinite(clear), clear, 1e3).min((2, 3))
        fallback = self._latest(t_hit, worst)
        self.debug = dict(ok=ok, t_hit=t_hit, worst=worst, steer_first=steer_first)
        # a stop lasts until going on (or steering round) is clear: no creeping up on a car that
        # waits for the ego (it would wait as long as the ego creeps)
        order_stopped = [0, *np.flatnonzero(shift & np.isinf(speed)), stop]
        order_stopped_standing = [0, *np.flatnonzero(shift), stop]  # round a standing car at any speed
        stopped = (self.choice == stop) & (w.time > 1e-9) & (self.stop_at <= w.time)
        fresh = stopped & (w.time - self.stop_at < STOP_MIN_S - 1e-9)
        held = self._waited_for(rx, ry, ryaw, e_s, np.array([r.width for r in roads]))
        choice = np.empty(N, np.int64)
        for n in range(N):
            if stopped[n] and (held[n] or fresh[n]):  # stood for a crawling car: until it goes (or has crossed)
                choice[n] = stop
                continue
            if stopped[n]:
                order = order_stopped_standing if standing[n] else order_stopped
            else:
                order = order_steer if steer_first[n] else order_wait if waiting[n] else order_slow
            # the first clear one; else the first without contact; else the latest contact
            good = [m for m in order if ok[n, m]] or [m for m in order if touch_free[n, m]]
            choice[n] = good[0] if good else fallback[n]
        self.stop_at = np.where(choice != stop, np.inf, np.where(stopped, self.stop_at, w.time))
        self.choice = choice
        # throttle: full, a speed's throttle (brake above it), or the brake
        sp = speed[choice]
        thr = np.where(np.isinf(sp), 1.0, throttle_for_speed(np.where(np.isinf(sp), 0.0, sp), car, w.agent_speed_scale))
        thr = np.where((sp == 0.0) | (ev > sp + SLACK_V), -1.0, thr)
        # steering: pure pursuit of the chosen path ``look`` ahead (by arc)
        j = np.minimum(np.rint(look / PATH_DS).astype(np.int64), n_pts - 1)
        idx = np.arange(N)
        dx_r, dy_r = ps[idx, choice, j], pl[idx, choice, j] - e_l
        # into the ego's frame (road frame rotated by its heading off the road)
        cp, sp_ = np.cos(psi0), np.sin(psi0)
        lx, ly = dx_r * cp + dy_r * sp_, -dx_r * sp_ + dy_r * cp
        alpha = np.arctan2(ly, lx)
        ld = np.maximum(np.hypot(lx, ly), 1e-3)
        delta = np.arctan(2.0 * car.wheelbase * np.sin(alpha) / ld)
        steer = np.clip(delta, car.delta_min, car.delta_max) / car.steer_gain
        return np.stack([thr, steer], 1).astype(np.float32)

    def _seen(self) -> np.ndarray:
        """(N, A) the actors the teacher reacts to: seen by the ego's lidar within SEEN_MEMORY_S.
        The policy it teaches sees only its scans: a label for a car behind a wall, beyond the
        range or outside the view is one the policy cannot tell from a free road (it learned to
        stand at empty junctions)."""
        w = self.w
        A = w.actors.n_actors
        if self.seen_at.shape[1] != A:  # the batch's widest map changed (maps redrawn)
            self.seen_at = np.full((w.n_envs, A), -np.inf)
        self.seen_at[w.time < self.last_time - 1e-9] = -np.inf  # a new episode
        self.last_time = w.time.copy()
        now = w.seen()
        self.seen_at[now] = np.broadcast_to(w.time[:, None], now.shape)[now]
        return w.time[:, None] - self.seen_at <= SEEN_MEMORY_S + 1e-9

    @staticmethod
    def _latest(t_hit: np.ndarray, worst: np.ndarray) -> np.ndarray:
        key = t_hit * 1e4 + np.clip(worst, -1e3, 1e3)
        return key.argmax(1)

    def _clearance(self, gx, gy, gyaw, ax, ay, ayaw) -> np.ndarray:
        """(N, M, A, T) the smallest distance between the ego's and each actor's circles, minus
        both radii (inf for an unused actor slot)."""
        used = np.concatenate([self.w.actors.used] * (ax.shape[1] // self.w.actors.n_actors), 1)
        return _clearance(gx, gy, gyaw, ax, ay, ayaw, used, self.c_off, 2 * self.c_r)

    def _waited_for(self, rx, ry, ryaw, e_s, width) -> np.ndarray:
        """(N,) a crossing car crawls towards the ego's road ahead of it, near, slower than its
        own speed: a car that waits for the ego (as a synchronised scenario actor does) or edges
        out (a slow car at its own speed is predicted well: no wait). Once the ego has stopped
        for it, it stays stopped until the car goes faster or has crossed; going on as soon as a
        prediction at the crawl says clear makes the car wait again (it waits as long as the ego
        creeps)."""
        a = self.w.actors
        c, s = np.cos(ryaw)[:, None], np.sin(ryaw)[:, None]
        along_a = (a.x - rx[:, None]) * c + (a.y - ry[:, None]) * s
        lat_a = -(a.x - rx[:, None]) * s + (a.y - ry[:, None]) * c
        rel = a.yaw - ryaw[:, None]
        v = a.v * a.started
        crossing = np.abs(np.sin(rel)) >= ALONG_SIN
        towards = (lat_a * np.sin(rel) < 0) | (np.abs(lat_a) < width[:, None] / 2)
        ahead = (along_a > e_s[:, None] - 0.5) & (along_a < e_s[:, None] + WAIT_RANGE_M)
        crawl = (v >= STILL_V) & (v < CRAWL_V) & (v < 0.8 * a.v0)  # slowed below its own speed
        # a car no longer timed by the ego (released: at the conflict point, or on a scripted speed)
        # keeps the speed it has: the prediction covers it, and waiting on it froze the ego for
        # seconds while it crawled through (the conflict suite's crossings: 55-80 % frozen)
        return (a.used & crossing & towards & ahead & crawl & ~a.released).any(1)

    def _steer_first(self, who: np.ndarray, ryaw: np.ndarray, v_meet: np.ndarray) -> tuple[np.ndarray, ...]:
        """(steer first, standing, waiting) (N,): the car the full-throttle plan meets first is one
        to steer round: standing where they would meet (``v_meet``, its predicted speed then),
        coming at the ego along its road, or going its way slower than CRAWL_V; or one to wait
        for: crossing the ego's road, moving slower than CRAWL_V."""
        w = self.w
        idx = np.arange(w.n_envs)
        v = w.actors.v[idx, who] * w.actors.started[idx, who]
        rel = w.actors.yaw[idx, who] - ryaw
        along = np.abs(np.sin(rel)) < ALONG_SIN
        standing = (v_meet < STILL_V) | (v < STILL_V)
        coming = along & (np.cos(rel) < 0)
        crawling = along & (np.cos(rel) > 0) & (v < CRAWL_V)
        waiting = ~along & (v >= STILL_V) & (v < CRAWL_V)
        return standing | coming | crawling, standing, waiting & ~standing


# ---------------------------------------------------------------------------------- the probe
def student_car(view: str = VIEW):
    """The shipped car scanning with the lidar ``view`` (common/lidar.VIEWS), built by the training
    env's own function: the teacher's seen rule then answers the cars the student's scans return
    from, no fewer."""
    from racecav.common.config import EnvConfig
    from racecav.training.env import env_car

    return env_car(EnvConfig(lidar=view))


def drive(scenarios: list, trials: int, seed: int, driver: str, car=None, policy=None) -> dict[str, np.ndarray]:
    """Drive ``trials`` trials of each scenario (one FastWorld per scenario, seed ``seed + k``
    for the k-th) by ``driver``: "teacher" (its own labels), "straight" (1 m/s) or "full"
    (full throttle), both references straight along the start heading, or "policy" (``policy``,
    a NumpyPolicy, on its stacked scans: a student beside its teacher on the same trials).
    ``car``: default the shipped car scanning with the student's lidar view (:func:`student_car`).

    :return: per trial (scenarios x trials, flattened): success, collided, frozen (no contact
        but short of the route at the end), from_rest (the ego started standing), drive_off (s
        until it first exceeded 0.2 m/s; nan if never), done_at (s until it first had the route's
        progress without contact; nan if never).
    """
    from racecav.common.policy import push_scans, stacked_scans
    from racecav.sim.fast_world import FastWorld
    from racecav.training.teacher import tracking_steer

    if (driver == "policy") != (policy is not None):
        raise ValueError("drive: a policy goes with the policy driver, and only with it")
    car = car or student_car()
    keys = ("success", "collided", "frozen", "from_rest", "drive_off", "done_at")
    out: dict[str, list] = {k: [] for k in keys}
    for k, sc in enumerate(scenarios):
        fw = FastWorld(n_envs=trials, scenarios=[sc], car=car, seed=seed + k)
        if policy is None:
            fw.observe[:] = False  # nothing here reads a scan
        obs = fw.reset()
        teacher = PredictiveTeacher(fw) if driver == "teacher" else None
        if policy is not None:  # its scans newest first, obs_stride apart, as in training
            n_stack, stride = policy.obs_stack, policy.obs_stride
            hist = np.repeat(np.asarray(obs, np.float32)[:, None], (n_stack - 1) * stride + 1, axis=1)
        thr = 1.0 if driver == "full" else float(throttle_for_speed(1.0, car, fw.agent_speed_scale))
        hit = np.zeros(trials, bool)
        live = np.ones(trials, bool)
        rest = fw.v[:, 0] < STILL_V
        off = np.full(trials, np.nan)
        done_at = np.full(trials, np.nan)
        while live.any():
            if teacher is not None:
                a = teacher.labels().astype(np.float64)
            elif policy is not None:
                a = policy(stacked_scans(hist, n_stack, stride)).astype(np.float64)
            else:
                a = np.stack([np.full(trials, thr), tracking_steer(fw)], 1)
            a[~live] = 0.0
            bb = policy.brake_below if policy is not None else BRAKE_BELOW
            o, *_ = fw.step(a, brake=brake_from_action(a[:, 0], bb) & live, observe=policy is not None)
            if policy is not None:
                push_scans(hist, o)
            hit |= fw.collided & live
            moving = live & np.isnan(off) & (fw.v[:, 0] > 0.2)
            off[moving] = fw.time[moving]
            there = live & ~hit & np.isnan(done_at) & fw.success()
            done_at[there] = fw.time[there]
            live &= ~hit & (fw.time < fw.time_limit - 1e-9)
        ok = fw.success() & ~hit
        out["success"].append(ok)
        out["collided"].append(hit)
        out["frozen"].append(~ok & ~hit)
        out["from_rest"].append(rest)
        out["drive_off"].append(off)
        out["done_at"].append(done_at)
    return {k: np.concatenate(v) if v else np.zeros(0) for k, v in out.items()}


DRIVERS = {"teacher": "predictive teacher", "straight": "straight 1 m/s", "full": "full throttle"}


def probe(suite: str, splits: list[str], trials: int, seed: int, families: list[str] | None = None,
          progress: bool = True, policy=None) -> dict:
    """{split: {family: {driver: measures}}} of :func:`drive` on the files of a suite's splits
    (with ``policy``, a NumpyPolicy: its driver "policy" too, on the same trials)."""
    from tqdm import tqdm

    from racecav.common.scenario import load_scenario, open_suite

    s = open_suite(suite)
    res: dict = {}
    jobs = []
    for split in splits:
        if split not in s.manifest["splits"]:
            raise ValueError(f"--splits: suite {suite} has no split {split!r} (has {', '.join(s.manifest['splits'])})")
        by_fam: dict[str, list] = {}
        for f, fam in s.files(split):
            if families is None or fam in families:
                by_fam.setdefault(fam, []).append(f)
        for fam, files in by_fam.items():
            jobs.append((split, fam, files))
    drivers = [*DRIVERS, *(["policy"] if policy is not None else [])]
    car = student_car(policy.metadata.get("lidar", "paper")) if policy is not None else None
    bar = tqdm(total=sum(len(j[2]) for j in jobs) * len(drivers), desc="teacher probe", unit="file",
               disable=not progress)
    for split, fam, files in jobs:
        scs = [load_scenario(f) for f in files]
        # the same seeds for every driver: the same trials
        base = seed + 1009 * (sorted(s.manifest["splits"]).index(split) + 1)
        for d in drivers:
            res.setdefault(split, {}).setdefault(fam, {})[d] = drive(scs, trials, base, d, car,
                                                                     policy if d == "policy" else None)
            bar.update(len(files))
    bar.close()
    return res


def _pct(x: np.ndarray) -> str:
    return f"{100 * x.mean():.0f}" if len(x) else "-"


def report(res: dict, command: str, controls: set[str] = frozenset(), policy_name: str = "") -> str:
    """The markdown of docs/teacher.md (with a policy's columns when ``res`` has its driver)."""
    lines = ["# The predictive teacher, driven by its own labels", "",
             "Generated by `" + command + "` (training/predictive_teacher.py). Fast world, the student's "
             f"lidar view ({VIEW}: the teacher answers the cars its scans return from), selection seeds "
             f"(from {SELECTION_SEED}; the table's test trials use seeds from 0), the same trials for every driver. "
             "Success: no contact and the route's progress; collisions: any contact; frozen: no contact but "
             "short of the route when the trial's time ran out; drive-off: time until the ego first exceeds "
             "0.2 m/s, over the trials that start at rest. The references drive straight along their start "
             "heading at 1 m/s or at full throttle.", ""]
    student = any("policy" in fam for fams in res.values() for fam in fams.values())
    if student:
        lines += [f"The policy: {policy_name} (its own view and stack, driven by its mean action).", ""]
    pcols = " policy success % | policy collisions % | policy frozen % |" if student else ""
    lines += ["## Per split (mean over families)", "",
              "| split | trials | teacher success % | collisions % | frozen % |" + pcols
              + " straight 1 m/s % | full throttle % | drive-off from rest (median / max s, trials) |",
              "|---|---:|---:|---:|---:|" + ("---:|---:|---:|" if student else "") + "---:|---:|---|"]
    for split, fams in res.items():
        def fam_mean(d, key):
            return f"{100 * np.mean([fams[f][d][key].mean() for f in fams]):.0f}"
        n = sum(len(fams[f]["teacher"]["success"]) for f in fams)
        rest = np.concatenate([fams[f]["teacher"]["drive_off"][fams[f]["teacher"]["from_rest"]] for f in fams])
        off = (f"{np.nanmedian(rest):.1f} / {np.nanmax(rest):.1f} ({len(rest)}, never: {int(np.isnan(rest).sum())})"
               if len(rest) and not np.isnan(rest).all() else ("never" if len(rest) else "-"))
        pol = (f" {fam_mean('policy', 'success')} | {fam_mean('policy', 'collided')} | {fam_mean('policy', 'frozen')} |"
               if student else "")
        lines.append(f"| {split} | {n} | {fam_mean('teacher', 'success')} | {fam_mean('teacher', 'collided')} | "
                     f"{fam_mean('teacher', 'frozen')} |{pol} {fam_mean('straight', 'success')} | "
                     f"{fam_mean('full', 'success')} | {off} |")
    for split, fams in res.items():
        lines += ["", f"## {split}", "",
                  "| family | trials | teacher success % | collisions % | frozen % |"
                  + (" policy success % (coll. / frozen) |" if student else "")
                  + " straight 1 m/s % (coll.) | full throttle % (coll.) |",
                  "|---|---:|---:|---:|---:|" + ("---:|" if student else "") + "---:|---:|"]
        for fam in sorted(fams):
            t, a, b = (fams[fam][d] for d in DRIVERS)
            pol = ""
            if student:
                q = fams[fam]["policy"]
                pol = f" {_pct(q['success'])} ({_pct(q['collided'])} / {_pct(q['frozen'])}) |"
            lines.append(f"| {fam} | {len(t['success'])} | {_pct(t['success'])} | {_pct(t['collided'])} | "
                         f"{_pct(t['frozen'])} |{pol} {_pct(a['success'])} ({_pct(a['collided'])}) | "
                         f"{_pct(b['success'])} ({_pct(b['collided'])}) |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m racecav.training.predictive_teacher",
                                description="the predictive teacher driven by its own labels in the fast world, per "
                                            "family and split, beside both non-evading references on the same seeds")
    p.add_argument("--suite", required=True, help="suite NAME (runs/suites/NAME) or folder with suite.json")
    p.add_argument("--splits", default="test,ood,controls", help="comma-separated splits")
    p.add_argument("--trials", type=int, default=2, help="trials per file")
    p.add_argument("--seed", type=int, default=SELECTION_SEED)
    p.add_argument("--families", default="", help="only these families (comma-separated; default all)")
    p.add_argument("--policy", help="also drive this policy (a shipped name or .npz, or a run's checkpoint .zip) "
                                    "on the same trials: a student beside its teacher")
    p.add_argument("--out", help="write the markdown here (else print it)")
    p.add_argument("--no-progress", action="store_true")
    args = p.parse_args(argv)
    if args.trials < 1:
        print("--trials: must be >= 1", file=sys.stderr)
        return 2
    splits = [x.strip() for x in args.splits.split(",") if x.strip()]
    fams = [x.strip() for x in args.families.split(",") if x.strip()] or None
    try:
        policy = None
        if args.policy:
            from racecav.training.policy_io import named_policy

            policy = named_policy(args.policy)
        res = probe(args.suite, splits, args.trials, args.seed, fams, progress=not args.no_progress, policy=policy)
    except (ValueError, FileNotFoundError) as e:
        print(str(e), file=sys.stderr)
        return 2
    cmd = "python -m racecav.training.predictive_teacher " + " ".join(argv if argv is not None else sys.argv[1:])
    text = report(res, cmd.strip(), policy_name=args.policy or "")
    if args.out:
        Path(args.out).write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
