"""A privileged planner for the fast world: the teacher of ``racecav train dagger``.

The planner sees what the policy cannot: the world's state, including every obstacle car's and
scenario actor's future (it steps an exact copy of the world). At each control step it copies
each of the N worlds once per candidate manoeuvre into a planning FastWorld of N x K worlds
(no lidar), drives every copy ``horizon_s`` ahead and returns, per world, the first action of
the best candidate: a receding-horizon search over motion primitives, the dynamic-window idea
(Fox et al. 1997) with an exact prediction instead of a constant-velocity one.

A candidate holds a steering action for ``hold`` control steps, then drives on under a tracking
steer (full throttle throughout): back to the ego's initial heading in a scenario world, a
pure pursuit of the centerline (in the ego's direction) in a traffic world. Its score is its
progress at the horizon (the quantity the episode's success and the progress reward count),
minus a penalty for a clearance to other cars under ``margin_m`` and, in scenario worlds, for
the lateral offset from the ego's road; a candidate that touches anything scores below every
one that does not, later contacts above earlier ones.
"""

from __future__ import annotations

import numpy as np

from racecav.sim import fast_kernels as K
from racecav.sim.fast_world import FastWorld
from racecav.sim.traffic import CenterlineDriver

# candidate manoeuvres: steering actions within the car's range (rad, steer_gain 1) held for
# one of two times (control steps), at full throttle. The paper's action cannot brake, and a
# policy fitted to a mix of full-throttle and coasting labels learns the mean, a part throttle
# that no plan chose (0.6-0.9 in a first run, too slow for the paper-timed crossings).
STEER_FRACTIONS = (-1.0, -0.5, -0.2, 0.0, 0.2, 0.5, 1.0)
THROTTLES = (1.0,)
HOLDS = (3, 8)
HEADING_GAIN = 0.8    # rad of steering per rad of heading error (scenario worlds' tracking steer) ...
YAW_RATE_GAIN = 0.15  # ... minus this per rad/s of yaw rate: 1.5 without damping oscillates with
                      # the steering lag (+-0.08 rad every step, labels a policy cannot imitate)
MARGIN_M = 0.35       # clearance (m, between box centres minus a car length) below which a plan pays
CLEARANCE_WEIGHT = 4.0  # score per metre of clearance missing
LATERAL_WEIGHT = 0.3    # score per metre of lateral offset from the ego's road (scenario worlds)
CONTACT_SCORE = -1000.0
TIE_M = 0.1  # score (m) within which the planner keeps tracking, else its previous manoeuvre
GEOMETRY = {"walls", "wall_box", "faces", "chunks", "cl", "mount", "ray_c", "ray_s", "ray_t",
            "observe", "ranges"}
"""FastWorld arrays that are not per-world state (or that the planner does not need)."""


def candidates(car) -> np.ndarray:
    """(K, 3) a_T, a_delta, hold steps; the first is "track at full throttle" (hold 0)."""
    rows = [(1.0, 0.0, 0)]
    for t in THROTTLES:
        for f in STEER_FRACTIONS:
            steer = f * (car.delta_max if f > 0 else -car.delta_min) / car.steer_gain
            for h in (HOLDS if f != 0.0 else HOLDS[-1:]):
                rows.append((t, steer, h))
    return np.array(rows, dtype=np.float64)


def latch_seen(world: FastWorld, seen: np.ndarray, envs: np.ndarray) -> np.ndarray:
    """``seen`` (one bool per world of ``envs``) latched by this step: cleared where a new
    episode starts, set where a car returns a ray of the ego's scan (FastWorld.seen_by_agent;
    only the worlds not yet latched are scanned). Call it at every step: the latch must see each
    step's scan. Returns the new flags."""
    seen = seen & (world.time[envs] >= 1e-9)  # a new episode: nothing seen yet
    todo = np.flatnonzero(~seen)
    if todo.size:
        seen[todo] = world.seen_by_agent(envs[todo]).any(axis=1)
    return seen


def tracking_steer(p: FastWorld) -> np.ndarray:
    """(N,) the tracking steer action of every world's ego: a damped hold of the ego's initial
    heading in a scenario world, the traffic driver's pure pursuit of the centerline (in the
    ego's direction) in a traffic world."""
    car = p.car
    if p.actors is not None:
        err = np.angle(np.exp(1j * (p.start_pose[:, 2] - p.yaw[:, 0])))
        steer = HEADING_GAIN * err - YAW_RATE_GAIN * p.r[:, 0]
    else:
        n = p.n_envs
        out = np.zeros((n, 1, 2))
        K.pure_pursuit(p.x[:, :1], p.y[:, :1], p.yaw[:, :1], p.v[:, :1], p.active[:, :1], p.cl_idx[:, :1],
                       np.zeros((n, 1)), np.ones((n, 1)), p.cl, p.cl_ds, car.wheelbase, car.steer_gain,
                       car.v_max, 3.0, car.width, 0, -1 if p.heading == "reversed" else 1, out)
        steer = out[:, 0, 1] * car.steer_gain
    return np.clip(steer, car.delta_min, car.delta_max) / car.steer_gain


class Expert:
    """The planner of one FastWorld (a traffic or a scenario world of a FastVecEnv batch).

    :param world: the FastWorld whose agents it plans for (read, never changed).
    :param horizon_s: look-ahead (s).
    :param envs: plan for these of its worlds only (default: all of them).
    :param track_only: the first candidate only (plain tracking): ``scores`` then tells whether the
        ego's lane is free (training/lane_keeping.py).
    :param commit_s: ``act`` chooses a manoeuvre only where plain tracking touches something within
        this time (s), and tracks elsewhere: labels that evade only once a conflict is certain
        (None: wherever a manoeuvre scores better).
    :param seen_only: ``act`` tracks in a scenario world until a car has returned a ray of its
        ego's scan in this episode (FastWorld.seen_by_agent, latched by ``update_seen``): labels
        that answer only a car the policy has seen. Why: held straight until the car first
        returns a ray, the planner passes every paper-timed crossing from the left (that car stays
        hidden from a straight fast ego) and 75-77 % of the conflict-timed ones (docs/training.md,
        the probe of row 31); the unrestricted planner moves before anything is in view, which no
        policy of the scans can imitate. Measured (row 49): imitating these labels still collapses
        the policy, as rows 15 and 20 did.
    """

    def __init__(self, world: FastWorld, horizon_s: float = 2.5, envs=None, track_only: bool = False,
                 commit_s: float | None = None, seen_only: bool = False):
        scen = world.actors is not None
        if not scen and world.n_obstacles and not isinstance(world.driver, CenterlineDriver):
            # the copies must move the traffic as the world does; a policy driver would need scans
            raise ValueError("the planner predicts traffic driven by the centerline driver only (--driver centerline)")
        self.src = world
        self.envs = np.arange(world.n_envs) if envs is None else np.asarray(envs, dtype=np.int64)
        self.n = len(self.envs)
        self.cands = candidates(world.car)[:1] if track_only else candidates(world.car)
        self.k = len(self.cands)
        self.h = int(round(horizon_s / world.control_period))
        self.commit = None if commit_s is None else int(round(commit_s / world.control_period))
        self.seen_only = seen_only and scen
        self.seen = np.zeros(self.n, dtype=bool)  # seen_only: a car has been in view this episode
        self.plan = FastWorld(n_envs=self.n * self.k, world=world.world, car=world.car,
                              n_obstacles=world.n_obstacles, heading=world.heading,
                              driver="centerline", obstacle_lidar=False,
                              agent_speed_scale=world.agent_speed_scale,
                              control_period=world.control_period, physics_substeps=world.substeps,
                              scenarios=world.scenarios if scen else None)
        self.plan.observe[:] = False  # no lidar: the planner reads the state
        self.scenario = scen
        self.last_best = np.zeros(self.n, dtype=np.int64)

    def _copy_state(self) -> None:
        k = self.k
        for obj, dst in ((self.src, self.plan), (self.src.actors, self.plan.actors)):
            if obj is None:
                continue
            n = obj.n_envs
            for name, val in vars(obj).items():
                if isinstance(val, np.ndarray) and val.ndim and val.shape[0] == n and name not in GEOMETRY:
                    setattr(dst, name, np.repeat(val[self.envs], k, axis=0))

    def _track(self) -> np.ndarray:
        """(N*K,) tracking steer action of every planning world's ego."""
        return tracking_steer(self.plan)

    def scores(self) -> np.ndarray:
        """(n, K) each candidate's score from the source world's current state."""
        self._copy_state()
        p, n, k = self.plan, self.n, self.k
        cand = np.tile(self.cands, (n, 1))
        hit = np.full(n * k, np.inf)
        short = np.full(n * k, np.inf)  # smallest clearance to another car seen
        prog0 = p.progress()
        act = np.empty((n * k, 2))
        length = p.car.length
        for step in range(self.h):
            hold = step < cand[:, 2]
            track = self._track()
            if step == 0:
                self.first_track = track.reshape(n, k)[:, 0].copy()
            act[:, 0] = np.where(hold, cand[:, 0], 1.0)
            act[:, 1] = np.where(hold, cand[:, 1], track)
            _, _, col, _ = p.step(act, observe=False)
            hit = np.where(col & np.isinf(hit), step, hit)
            if p.n_cars > 1:
                d = np.hypot(p.x[:, 1:] - p.x[:, :1], p.y[:, 1:] - p.y[:, :1])
                d = np.where(p.active[:, 1:], d, np.inf).min(axis=1) - length
                short = np.minimum(short, d)
        score = p.progress() - prog0
        score -= CLEARANCE_WEIGHT * np.maximum(MARGIN_M - short, 0.0)
        if self.scenario:
            x0, y0, yaw0 = p.start_pose.T
            lat = -(p.x[:, 0] - x0) * np.sin(yaw0) + (p.y[:, 0] - y0) * np.cos(yaw0)
            score -= LATERAL_WEIGHT * np.abs(lat)
        score = np.where(np.isfinite(hit), CONTACT_SCORE + hit, score)
        return score.reshape(n, k)

    def update_seen(self) -> None:
        """seen_only: latch, per world, that a car has returned a ray of its ego's scan in this
        episode (once seen, an evasion goes on when the car is out of view). Call it at every
        step when ``act`` labels only some of them."""
        self.seen = latch_seen(self.src, self.seen, self.envs)

    def act(self) -> np.ndarray:
        """(n, 2) the best candidate's first action in each planned world: plain tracking unless a
        manoeuvre scores more than TIE_M better, and the previous manoeuvre unless another does
        (labels that do not flip between near-equal plans are easier to imitate)."""
        s = self.scores()
        self.last_best[self.src.time[self.envs] < 1e-9] = 0  # a new episode
        best = s.argmax(axis=1)
        rows = np.arange(len(best))
        top = s[rows, best]
        keep = s[rows, self.last_best] >= top - TIE_M
        best = np.where(keep, self.last_best, best)
        best = np.where(s[:, 0] >= top - TIE_M, 0, best)
        if self.commit is not None:  # tracking's contact step (the score encodes it), inf if none
            hit = np.where(s[:, 0] < CONTACT_SCORE / 2, s[:, 0] - CONTACT_SCORE, np.inf)
            best = np.where(hit >= self.commit, 0, best)
        if self.seen_only:  # nothing in view yet this episode: tracking
            self.update_seen()
            best = np.where(self.seen, best, 0)
        self.last_best = best
        c = self.cands[best]
        first = np.where(c[:, 2] == 0, self.first_track, c[:, 1])
        return np.stack([c[:, 0], first], axis=1)
