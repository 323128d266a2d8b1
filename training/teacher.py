"""The yield teacher of ``racecav train dagger`` (the shipped avoid's, rows 91-95 of docs/training.md).

The teacher is the frozen ``init_from`` policy, relabelled in the worlds that run a scenario of
one of ``families``: full throttle along the ego's road, the brake only while a car *in the ego's
scan* is in the crossing or closing on it (so the label changes only where the scan shows a car:
an intersection with no car in view is driven through at full throttle, like the paper-timed
crossings a fast ego passes first), the speed of a gap behind a car in its scan that is ahead in
its lane and going its way (:meth:`YieldTeacher._follow`: a car that turned into the lane ahead),
and a steer round a car in its scan that blocks its path, oncoming or stopped
(:meth:`YieldTeacher._dodge`). A car along the ego's road, e.g. an oncoming one in the other
lane, is busy only within ONCOMING_M. It reads where the cars are (privileged, training only);
the fitted policy sees only its scans. Elsewhere the label is the policy's own action.

The ablation's other teachers (a privileged planner, the policy's mirror image, tracking, hold,
stop and look) are in the history at commit 3a95a65 (docs/training.md).
"""

from __future__ import annotations

import numpy as np

HEADING_GAIN = 0.8    # rad of steering per rad of heading error (scenario worlds' tracking steer) ...
YAW_RATE_GAIN = 0.15  # ... minus this per rad/s of yaw rate: 1.5 without damping oscillates with
                      # the steering lag (+-0.08 rad every step, labels a policy cannot imitate)
# yield waits while a car in the ego's scan is within BOX_M of the conflict point or within
# APPROACH_M and closing on it (the values of the fast-world probe of rows 78-79 in docs/training.md).
BOX_M, APPROACH_M = 0.8, 3.5
STOPPED_V = 0.05  # m/s: a car below it has stopped (yield's busy test counts it as moving above)
# yield follows a car in the ego's scan that is ahead in its lane and going its way (e.g. one that
# turned into the lane ahead): within FOLLOW_M ahead and LANE_M aside, headings within 60 deg; the
# speed it asks for: the car's plus FOLLOW_GAIN per metre of gap beyond FOLLOW_GAP_M (centres).
FOLLOW_M, LANE_M, FOLLOW_GAP_M, FOLLOW_GAIN = 3.0, 0.4, 0.8, 2.0
ONCOMING_M, ALONG_SIN = 2.0, 0.2  # yield's reach for a car along the ego's road (|sin| of its heading)
# yield steers round a car in its scan that blocks its path ahead (oncoming or stopped) within
# DODGE_M or DODGE_S of closing: to DODGE_CLEAR_M beside the car's extent, on the side away from it
# unless the road (ROAD_HALF_M either side of y = 0, the scenario worlds' road centre) has no room
# there; a heading of DODGE_GAIN rad per m of lateral error, steered at DODGE_STEER_GAIN rad per
# rad of heading error (a firmer hand than the tracking steer's: the manoeuvre is short)
DODGE_M, DODGE_S, DODGE_CLEAR_M, ROAD_HALF_M, DODGE_GAIN, DODGE_STEER_GAIN = 3.5, 2.0, 0.35, 0.95, 1.5, 2.0
KEEP_RIGHT_M = 0.25  # m: a car less than this to the ego's right is passed on its right side too
DODGE_MAX_RAD = 0.25  # rad: the dodge's largest heading off the road's
DODGE_HOLD_M = 0.1  # m: a car counts as blocking up to this beyond DODGE_CLEAR_M beside the ego




def tracking_steer(p) -> np.ndarray:
    """(N,) the tracking steer action of every scenario world's ego: a damped hold of its
    initial heading (its road's)."""
    car = p.car
    err = np.angle(np.exp(1j * (p.start_pose[:, 2] - p.yaw[:, 0])))
    steer = HEADING_GAIN * err - YAW_RATE_GAIN * p.r[:, 0]
    return np.clip(steer, car.delta_min, car.delta_max) / car.steer_gain


def _acted(policy, obs: np.ndarray, coast_only: bool) -> np.ndarray:
    """``policy``'s actions on ``obs`` as labels; ``coast_only``: a policy trained without a brake,
    whose a_T < 0 (a coast for it) is labelled 0 (a coast under the run's brake too)."""
    out = np.array(policy(obs), copy=True)
    if coast_only:
        out[:, 0] = np.maximum(out[:, 0], 0.0)
    return out


class YieldTeacher:
    """Labels for the worlds of a FastVecEnv: the frozen ``policy`` (a NumpyPolicy with its own
    normalisation) on raw scans, relabelled by yield in the worlds that run a scenario of ``families``.

    :param families: family names without the suite (``cross-left`` matches every suite's) or with it.
    :param teacher_brakes: whether ``policy`` was trained with a brake. Without one its a_T < 0 is a
        coast, which the run's brake would read as a brake below brake_below: its own actions are
        labelled with a_T >= 0 then (a coast here too).
    :raises ValueError: when no scenario of the env belongs to one of ``families`` (a typo would
        otherwise label nothing and fit the policy to itself), or the run has no brake.
    """

    def __init__(self, policy, fast_env, families: list[str], teacher_brakes: bool = True):
        if fast_env.settings.brake_below is None:
            raise ValueError("--expert yield brakes: set --brake-below (the run's policy needs a brake)")
        self.policy, self.fast = policy, fast_env
        self.coast_only = not teacher_brakes
        qualified = {f for w in fast_env.worlds if w.actors is not None for f in w.scenario_families}
        have = sorted(qualified | {f.split("/")[-1] for f in qualified})
        unknown = [f for f in families if f not in have]
        if not families or unknown:
            raise ValueError(f"--mirror-families: {unknown or families} not among the scenario families {have}")
        self.families = set(families)
        # per world: a bool per scenario file, True where its family is relabelled
        self._mine = [None if w.actors is None else np.array([f in self.families or f.split("/")[-1] in self.families
                                                              for f in w.scenario_families])
                      for w in fast_env.worlds]
        self._dodging = [np.zeros(w.n_envs, bool) for w in fast_env.worlds]  # steered round a car last step
        self._held = np.zeros(fast_env.num_envs, bool)
        self._steered = np.zeros(fast_env.num_envs, bool)

    def _yield(self) -> tuple[np.ndarray, np.ndarray]:
        """(labelled (N,), throttle label (N,)): the worlds of ``families`` whose ego is short of the
        crossing's centre or follows or steers round a car, and the throttle there (+1 go, -1
        brake, or the follow's); the steer is kept in ``self._steer`` (NaN: the road's tracking
        steer). Call it at every step: the latches follow each world's episode."""
        lab, thr, steers = [], [], []
        for k, (w, m) in enumerate(zip(self.fast.worlds, self._mine)):
            steer = np.full(w.n_envs, np.nan)  # NaN: the road's tracking steer
            if m is None:
                lab.append(np.zeros(w.n_envs, bool))
                thr.append(np.ones(w.n_envs))
                steers.append(steer)
                continue
            new = w.time < 1e-9  # a new episode: nothing latched
            dodging = self._dodging[k]
            dodging[new] = False
            short = m[w.scenario_index] & (w.x[:, 0] < 0.0)
            brake = np.zeros(w.n_envs, bool)  # exactly while a seen car is busy
            look = np.flatnonzero(short)
            if look.size:
                brake[look] = self._busy(w, look)
            throttle = np.where(brake, -1.0, 1.0)
            # a car ahead in the lane going the ego's way is followed wherever the ego is
            look = np.flatnonzero(m[w.scenario_index])
            if look.size:
                follow, t_follow = self._follow(w, look)
                short[look[follow]] = True
                throttle[look[follow]] = np.minimum(throttle[look[follow]], t_follow[follow])
                # a car that blocks the path (oncoming or stopped) is passed, not waited for
                dodge, d_steer = self._dodge(w, look, dodging[look])
                dodging[:] = False
                dodging[look] = dodge
                short[look[dodge]] = True
                throttle[look[dodge]] = 1.0
                steer[look[dodge]] = d_steer[dodge]
            lab.append(short)
            thr.append(throttle)
            steers.append(steer)
        self._steer = np.concatenate(steers)
        self._steered = ~np.isnan(self._steer)
        return np.concatenate(lab), np.concatenate(thr)

    @staticmethod
    def _from_conflict(w, look: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(dx, dy, distance), each (len(look), n_actors): the actors from the conflict point (x = 0
        on the ego's road, the scenario convention)."""
        dx, dy = w.x[look, 1:], w.y[look, 1:] - w.start_pose[look, 1:2]
        return dx, dy, np.hypot(dx, dy)

    @staticmethod
    def _busy(w, look: np.ndarray) -> np.ndarray:
        """(len(look),) bool: a car in the ego's scan within BOX_M of the conflict point, or within
        APPROACH_M, moving and closing on it (the scenario's conflict point: x = 0 on the ego's road).
        A car along the ego's road (an oncoming one in the other lane, e.g. the turning family's
        left_across before its turn) is busy only within ONCOMING_M: it may turn across there."""
        dx, dy, d = YieldTeacher._from_conflict(w, look)
        sin = np.sin(w.yaw[look, 1:])
        closing = dx * np.cos(w.yaw[look, 1:]) + dy * sin < 0.0
        reach = np.where(np.abs(sin) < ALONG_SIN, ONCOMING_M, APPROACH_M)
        # a stopped car does not clear by waiting: it is steered round (_dodge), not waited for
        busy = ((d < BOX_M) | (closing & (d < reach))) & (w.v[look, 1:] > STOPPED_V)
        busy &= w.seen_by_agent(look)
        return busy.any(axis=1)

    @staticmethod
    def _follow(w, look: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(following (len(look),) bool, throttle label (len(look),)): the worlds whose ego has a
        car in its scan ahead in its lane going its way (within FOLLOW_M), and the label that keeps
        its distance: the throttle of the speed the gap asks for, the brake when the ego is more
        than 0.2 m/s above that speed. Why: a car that turned into the ego's lane ahead (the
        turning family's right_into) is past the crossing and not busy, and full throttle after
        it is a rear-end collision."""
        from racecav.common.vehicle import throttle_for_speed

        dx, dy = w.x[look, 1:] - w.x[look, :1], w.y[look, 1:] - w.y[look, :1]
        c, s = np.cos(w.yaw[look, :1]), np.sin(w.yaw[look, :1])
        ahead, aside = c * dx + s * dy, -s * dx + c * dy
        same_way = np.cos(w.yaw[look, 1:] - w.yaw[look, :1]) > 0.5
        lead = (ahead > 0.0) & (ahead < FOLLOW_M) & (np.abs(aside) < LANE_M) & same_way
        lead &= w.seen_by_agent(look)
        gap = np.where(lead, ahead, np.inf).min(axis=1)
        k = np.where(lead, ahead, np.inf).argmin(axis=1)
        v_lead = w.v[look, 1:][np.arange(len(look)), k]
        want = np.maximum(v_lead + FOLLOW_GAIN * (gap - FOLLOW_GAP_M), 0.0)
        throttle = np.where(w.v[look, 0] > want + 0.2, -1.0,
                            throttle_for_speed(np.minimum(want, w.car.v_max), w.car, w.car.agent_speed_scale))
        following = np.isfinite(gap)
        return following, np.where(following, throttle, 1.0)

    @staticmethod
    def _dodge(w, look: np.ndarray, holding: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(dodging (len(look),) bool, steer action (len(look),)): the worlds whose ego has a car
        in its scan within DODGE_M ahead, oncoming or stopped, whose extent across the ego's road
        overlaps the ego's path, and the steer towards DODGE_CLEAR_M beside it (a heading set by
        the lateral error, damped like the tracking steer). Why: such a car does not clear by
        waiting (an oncoming one synchronised to the ego keeps coming, a stopped one stays).
        ``holding`` (len(look),): the worlds that steered round a car at the last step; for them
        a car blocks until the ego is DODGE_CLEAR_M + DODGE_HOLD_M beside it, so the ego holds its
        side until it is past instead of braking once it is half out of the way."""
        car = w.car
        # in the road's frame, not the ego's: a path along the ego's heading leaves the car as soon
        # as the ego turns away, and the label would flip back to braking mid-manoeuvre
        road = w.start_pose[look, 2:3]
        dx, dy = w.x[look, 1:] - w.x[look, :1], w.y[look, 1:] - w.y[look, :1]
        c, s = np.cos(road), np.sin(road)
        ahead, aside = c * dx + s * dy, -s * dx + c * dy
        rel = w.yaw[look, 1:] - road
        v = w.v[look, 1:]
        # along the road towards the ego: a car turning across it is a crossing car, waited for (busy)
        oncoming = (np.cos(rel) < 0.0) & (np.abs(np.sin(rel)) < ALONG_SIN) & (v > STOPPED_V)
        stopped = v <= STOPPED_V
        half = 0.5 * (car.length * np.abs(np.sin(rel)) + car.width * np.abs(np.cos(rel)))  # across the road
        # where it will be across the road when the two meet (an oncoming car's heading may close in)
        closing = w.v[look, :1] * np.cos(w.yaw[look, :1] - road) - v * np.cos(rel)
        meet = np.clip(ahead / np.maximum(closing, 0.1), 0.0, DODGE_S)
        aside_then = aside + v * np.sin(rel) * meet
        reach = np.maximum(DODGE_M, DODGE_S * closing)
        # a new dodge: the car's extent overlaps the ego's path (a wider test would steer round
        # the turning family's oncoming cars, which yield waits for)
        beside = np.where(holding[:, None], DODGE_CLEAR_M + DODGE_HOLD_M, 0.1)
        near_path = np.minimum(np.abs(aside), np.abs(aside_then)) < half + car.width / 2 + beside
        blocks = (ahead > 0.0) & (ahead < reach) & near_path & (oncoming | stopped) & w.seen_by_agent(look)
        dodging = blocks.any(axis=1)
        k = np.where(blocks, ahead, np.inf).argmin(axis=1)
        i = np.arange(len(look))
        y_car = w.y[look, 1:][i, k] + (v * np.sin(w.yaw[look, 1:]))[i, k] * meet[i, k]
        room = half[i, k] + car.width / 2 + DODGE_CLEAR_M
        y_ego = w.y[look, 0]
        right, left = y_car - room, y_car + room
        # away from the car, unless the road has no room on that side; to the right of a car about
        # dead ahead (the side of right-hand traffic: a label that flips with a few cm of offset
        # would teach the mean of the two, straight on)
        go_left = np.where(y_ego - y_car >= KEEP_RIGHT_M, left <= ROAD_HALF_M, right < -ROAD_HALF_M)
        y_t = np.clip(np.where(go_left, left, right), -ROAD_HALF_M, ROAD_HALF_M)
        heading = w.start_pose[look, 2] + np.clip(DODGE_GAIN * (y_t - y_ego), -DODGE_MAX_RAD, DODGE_MAX_RAD)
        err = np.angle(np.exp(1j * (heading - w.yaw[look, 0])))
        steer = np.clip(DODGE_STEER_GAIN * err - YAW_RATE_GAIN * w.r[look, 0], car.delta_min, car.delta_max) / car.steer_gain
        return dodging, np.where(dodging, steer, 0.0)

    def in_families(self) -> np.ndarray:
        """(N,) bool: the worlds whose current episode runs a file of ``families``."""
        return np.concatenate([np.zeros(w.n_envs, bool) if m is None else m[w.scenario_index]
                               for w, m in zip(self.fast.worlds, self._mine)])

    def steered(self) -> np.ndarray:
        """(N,) bool: the steps of the newest :meth:`labels` where the label steers round a car
        (:meth:`_dodge`), a few per cent of its labels; ``--bc-balance`` gives them half of each
        imitation minibatch (training/dagger.py)."""
        return self._steered & self._held

    def labels(self, raw_obs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(labels (N, 2), relabelled (N,)) for the raw (not normalised) stacked scans ``raw_obs``:
        yield's throttle and steer on the relabelled steps, the policy's own action elsewhere."""
        self._held, throttle = self._yield()
        mask = self._held
        out = _acted(self.policy, raw_obs, self.coast_only)
        if mask.any():
            steer = np.concatenate([tracking_steer(w) if w.actors is not None else np.zeros(w.n_envs)
                                    for w in self.fast.worlds])
            steer = np.where(np.isnan(self._steer), steer, self._steer)
            out[mask] = np.stack([throttle[mask], steer[mask]], axis=1)
        return out, mask
