"""A policy's mirror image, and the mirror teacher of ``racecav train dagger --expert mirror``.

The intersection families come in mirror pairs (a car crossing from the left is a car crossing
from the right seen in a mirror: common/data/suites/*.toml draw both from the same ranges), yet
a trained policy is rarely symmetric. Row 16 (shipped as avoid 2026-12-01 to 02) passes 99 % of
the suites' crossings from the right and 75-81 % of those from the left in the fast world, while
the same network applied to the mirrored scans (steering negated) passes 96-99 % of those from
the left (``racecav train mirror``, training/checkpoints/mirror-avoid.md). The teacher labels
each step of a world whose scenario is of a ``families`` family (e.g. cross-left), once its car
is near on the ego's left, with that mirrored action, and every other step with the policy's own
action, so that DAgger (training/dagger.py) would fit one network to both: its skill on the
right, reflected onto the left, and everything else as it was. The teacher reads which family a
world runs and where its cars are (privileged, training only); the fitted policy sees only its
scans. Measured (docs/training.md, row 22): the fit does not keep everything else as it was.
Driven itself (``racecav train mirror``'s teacher rows), the teacher fails the crossings from the
left far more often than the policy or its mirror image alone: the mirrored turn has to begin
before the car is in view (rows 34-41 in docs/training.md).

Mirroring the scan reverses the ray order of each stacked scan. The wide view's rays are not
exactly symmetric about the heading (common/lidar.VIEWS: -168.5 to +167.5 paper increments), so
the reflection is off by one paper increment (0.53 deg), half the wide view's ray spacing.

``racecav train mirror --policy P`` measures a policy and its mirror image side by side on the
selection split (select.selection_cells, plus the paper-timed suite's train split).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np


def mirror_scans(obs: np.ndarray, obs_stack: int) -> np.ndarray:
    """The observations (..., obs_stack * n_rays) seen in a mirror: each scan's rays reversed."""
    obs = np.asarray(obs)
    n = obs.shape[-1] // obs_stack
    return obs.reshape(*obs.shape[:-1], obs_stack, n)[..., ::-1].reshape(obs.shape)


def mirror_action(action: np.ndarray) -> np.ndarray:
    """An action [a_T, a_delta] seen in a mirror: the steering negated."""
    out = np.array(action, dtype=np.float32, copy=True)
    out[..., 1] *= -1.0
    return out


RELABELS = ("mirror", "track", "hold", "stop", "yield")  # the --expert teachers that are the init_from policy, relabelled
NEAR_M = 5.0   # m: an actor this close (about where the crossings' cars come into view) ...
LEFT_M = 0.3   # m: ... and this far to the ego's left makes the scene a mirrored one
# --expert stop (stop and look): brake from STOP_M before the conflict point to below HALT_V, then
# wait while a car in the ego's scan is within BOX_M of the conflict point or within APPROACH_M
# and closing on it. The values of the fast-world probe in docs/training.md (rows 78-79).
STOP_M, HALT_V, BOX_M, APPROACH_M = 2.5, 0.15, 0.8, 3.5
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


class MirrorTeacher:
    """Labels for the worlds of a FastVecEnv: the frozen ``policy`` (a NumpyPolicy with its own
    normalisation) on raw scans, mirrored in the worlds that run a scenario of ``families``.

    :param families: family names without the suite (``cross-left`` matches every suite's).
    :param anchor_families: families whose steps with a car near on the ego's *right* the
        imitation term labels with the policy's own action (:meth:`anchored`), e.g. the mirror
        pair ``cross-right``, so that the reflected skill does not spill onto the side it came from.
    :param seen_only: label a near car only while it is in the ego's scan (FastWorld.seen_by_agent).
        The corners of the intersection hide a crossing car until the ego is about 2 m from the
        conflict point; before that the scans of a crossing from the left and from the right are
        the same, and mirrored labels there teach the mirrored turn for both sides.
    :param relabel: mirror: the mirrored action on those steps; track: plain tracking of the
        ego's road at full throttle (``--expert track``: e.g. ``paper-timed/cross-left``, the crossing
        a straight ego passes ahead of, which the policy turns into); hold: plain tracking at full
        throttle on every step of a ``families`` scenario before a car (on either side) has been
        in the ego's scan in the episode (``--expert hold``). Why: row 31 starts its turn before it
        can see the car, and that turn decides the crossings from the left; before a car is seen
        the scans of the two timings and of the two sides are the same, so one label fits all.
        Rows 52-53 of docs/training.md: fitting it moves the answers after the car is seen too.
        stop: stop and look, side-neutral (``--expert stop``, with a brake): on every step of a
        ``families`` scenario short of the crossing's centre, full throttle along the road until
        STOP_M before the conflict point, then the brake until the ego is below HALT_V, then the
        brake again while a car *in the ego's scan* is in the crossing or closing on it, then full
        throttle (the road's tracking steer throughout). Why: the crossing car of either timing
        and either side passes first (a synchronised one slows to its 0.5 m/s floor and goes by),
        so no turn begun before the car is in view is needed; it reads the cars only where the
        scan shows them, so a policy can learn it.
        yield: stop and look without the stop before the crossing: full throttle along the road,
        the brake only while a car *in the ego's scan* is in the crossing or closing on it (so
        the label changes only where the scan shows a car: an intersection with no car in view
        is driven through at full throttle, like the paper-timed crossings a fast ego passes first),
        and, wherever the ego is, the speed of a gap behind a car in its scan that is ahead in its
        lane and going its way (:meth:`_follow`: a car that turned into the lane ahead). A car along
        the ego's road, e.g. an oncoming one in the other lane, is busy only within ONCOMING_M.
        Its ``anchor_families`` get the same approach and keep their own answers: tracking at full
        throttle until a car has been in the ego's scan (short of the crossing), the policy's own
        action after it (:meth:`anchored`). Why: the approach scans of every intersection family
        are the same, so one label fits all of them; the families yield does not answer (a car
        ahead, oncoming or turning) keep the starting policy's evasion once that car is in view.
        A family in both ``families`` and ``anchor_families`` (e.g. ``braking``: a crossing car
        that stops across the ego's road) is yield's until a car in the ego's scan near the
        crossing has come to a stop, then anchored for the episode. Why: until it stops such a
        car looks like a crossing one (the same label: wait), and a stopped car does not clear
        by waiting (the starting policy's evasion, as for the stopped family).
    :param anchor_seen: relabel hold: :meth:`anchored` also returns every step of a ``families``
        scenario after its hold ended (a car seen, or the ego past the crossing's centre), whose
        label is the policy's own action: the answers after the car is in view are held where they
        were while the steps before it are fitted to the straight approach.
    :param teacher_brakes: whether ``policy`` was trained with a brake. Without one its a_T < 0 is a
        coast, which the run's brake would read as a brake below brake_below: its own actions are
        labelled with a_T >= 0 then (a coast here too).
    :raises ValueError: when no scenario of the env belongs to one of ``families`` (a typo would
        otherwise label nothing and fit the policy to itself).
    """

    def __init__(self, policy, fast_env, families: list[str], anchor_families: list[str] = (),
                 seen_only: bool = False, relabel: str = "mirror", anchor_seen: bool = False,
                 teacher_brakes: bool = True):
        if relabel not in RELABELS:
            raise ValueError(f"relabel: {' | '.join(RELABELS)}, not {relabel!r}")
        if relabel == "hold" and seen_only:
            raise ValueError("--expert hold labels the steps before a car is seen: --mirror-seen contradicts it")
        if anchor_seen and relabel != "hold":
            raise ValueError("--anchor-seen anchors the steps after --expert hold's labels: use it with --expert hold")
        if relabel in ("stop", "yield") and fast_env.settings.brake_below is None:
            raise ValueError(f"--expert {relabel} brakes: set --brake-below (the run's policy needs a brake)")
        self.policy, self.fast, self.seen_only, self.relabel = policy, fast_env, seen_only, relabel
        self.anchor_seen = anchor_seen
        self.coast_only = not teacher_brakes and fast_env.settings.brake_below is not None
        self.anchor_policy, self.anchor_coast_only = None, False
        qualified = {f for w in fast_env.worlds if w.actors is not None for f in w.scenario_families}
        have = sorted(qualified | {f.split("/")[-1] for f in qualified})
        for flag, names in (("--mirror-families", families), ("--anchor-families", anchor_families)):
            unknown = [f for f in names if f not in have]
            if (flag == "--mirror-families" and not names) or unknown:
                raise ValueError(f"{flag}: {unknown or names} not among the scenario families {have}")
        self.families, self.anchor_families = set(families), set(anchor_families)
        # per world: a bool per scenario file, True where its family is mirrored (anchored)
        self._mirrored = self._per_file(set(families))
        self._anchored = self._per_file(set(anchor_families))
        self._seen = [np.zeros(w.n_envs, bool) for w in fast_env.worlds]  # hold: latched per episode
        self._seen_anchor = [np.zeros(w.n_envs, bool) for w in fast_env.worlds]  # yield's anchor families
        self._held = np.zeros(fast_env.num_envs, bool)  # hold: the newest mirrored() mask
        # stop: per world, latched per episode: the ego has come down to HALT_V / has been let go
        self._halted = [np.zeros(w.n_envs, bool) for w in fast_env.worlds]
        self._go = [np.zeros(w.n_envs, bool) for w in fast_env.worlds]
        # yield: the families in both lists, and per world (latched per episode) a seen car stopped
        self._until_stop = self._per_file(self.families & self.anchor_families)
        self._stalled = [np.zeros(w.n_envs, bool) for w in fast_env.worlds]
        self._dodging = [np.zeros(w.n_envs, bool) for w in fast_env.worlds]  # yield steered round a car last step

    def set_anchor_policy(self, policy, teacher_brakes: bool) -> None:
        """Label the :meth:`anchored` steps with ``policy``'s actions instead of the teacher's
        (``--anchor-from``; ``teacher_brakes`` as in the constructor)."""
        self.anchor_policy = policy
        self.anchor_coast_only = not teacher_brakes and self.fast.settings.brake_below is not None

    def _per_file(self, names: set[str]) -> list[np.ndarray | None]:
        # a name matches its family in every suite (cross-left) or in one (paper-timed/cross-left)
        return [None if w.actors is None else np.array([f in names or f.split("/")[-1] in names
                                                         for f in w.scenario_families])
                for w in self.fast.worlds]

    def _near(self, per_file: list[np.ndarray | None], side: float) -> np.ndarray:
        """(N,) bool: a world running a file of ``per_file`` whose ego has an actor within
        ``NEAR_M`` on its left (``side`` +1) or right (-1), not behind it."""
        out = []
        for w, m in zip(self.fast.worlds, per_file):
            if m is None:
                out.append(np.zeros(w.n_envs, bool))
                continue
            dx, dy = w.x[:, 1:] - w.x[:, :1], w.y[:, 1:] - w.y[:, :1]
            c, s = np.cos(w.yaw[:, :1]), np.sin(w.yaw[:, :1])
            ahead, left = c * dx + s * dy, -s * dx + c * dy
            near = (np.hypot(dx, dy) < NEAR_M) & (side * left > LEFT_M) & (ahead > -0.5) & m[w.scenario_index, None]
            if self.seen_only:  # and in the ego's scan, not behind a corner (the same scan on both sides)
                envs = np.flatnonzero(near.any(axis=1))
                near[envs] &= w.seen_by_agent(envs)
            out.append(near.any(axis=1))
        return np.concatenate(out)

    def _unseen(self, per_file=None, latches=None) -> np.ndarray:
        """(N,) bool, relabel hold: the worlds running a file of ``families`` (or of ``per_file``,
        with its own ``latches``) in which no car has returned a ray of the ego's scan yet this
        episode and whose ego is short of the crossing's centre. Call it at every step
        (training/expert.latch_seen)."""
        from racecav.training.expert import latch_seen

        per_file = self._mirrored if per_file is None else per_file
        latches = self._seen if latches is None else latches
        if self.fast.hold_until_seen:  # the rollouts' own override: the same latch, kept by the env
            return self.fast.held & np.concatenate([np.zeros(w.n_envs, bool) if m is None else m[w.scenario_index]
                                                    for w, m in zip(self.fast.worlds, per_file)])
        out = []
        for w, m, seen in zip(self.fast.worlds, per_file, latches):
            if m is None:
                out.append(np.zeros(w.n_envs, bool))
                continue
            envs = np.flatnonzero(m[w.scenario_index])
            seen[envs] = latch_seen(w, seen[envs], envs)
            # up to the crossing's centre (every scenario's ego drives along +x to its conflict
            # point at x = 0): past it, holding the start heading means nothing
            out.append(~seen & m[w.scenario_index] & (w.x[:, 0] < 0.0))
        return np.concatenate(out)

    def _stop_and_look(self) -> tuple[np.ndarray, np.ndarray]:
        """(labelled (N,), throttle label (N,)), relabel stop or yield: the worlds of ``families``
        whose ego is short of the crossing's centre (yield: also wherever it follows or steers
        round a car), and the throttle there (+1 go, -1 brake); yield's own steer is kept in
        ``self._steer`` (NaN: the road's tracking steer). Call it at every step: the latches
        follow each world's episode."""
        lab, thr, steers = [], [], []
        for k, (w, m) in enumerate(zip(self.fast.worlds, self._mirrored)):
            steer = np.full(w.n_envs, np.nan)  # NaN: the road's tracking steer
            if m is None:
                lab.append(np.zeros(w.n_envs, bool))
                thr.append(np.ones(w.n_envs))
                steers.append(steer)
                continue
            new = w.time < 1e-9  # a new episode: nothing latched
            halted, go = self._halted[k], self._go[k]
            halted[new] = go[new] = False
            x, v = w.x[:, 0], w.v[:, 0]
            short = m[w.scenario_index] & (x < 0.0)
            if self.relabel == "yield":  # brake exactly while a seen car is busy
                stalled, dodging = self._stalled[k], self._dodging[k]
                stalled[new] = dodging[new] = False
                look = np.flatnonzero(short & ~stalled & self._until_stop[k][w.scenario_index])
                if look.size:
                    stalled[look] = self._stopped(w, look)
                short &= ~stalled  # from here the family's anchor (anchored())
                brake = np.zeros(w.n_envs, bool)
                look = np.flatnonzero(short)
                if look.size:
                    brake[look] = self._busy(w, look)
                throttle = np.where(brake, -1.0, 1.0)
                # a car ahead in the lane going the ego's way is followed wherever the ego is
                look = np.flatnonzero(m[w.scenario_index] & ~stalled)
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
                continue
            near = x >= -STOP_M
            halted |= near & (v < HALT_V)
            look = np.flatnonzero(halted & ~go & m[w.scenario_index])
            if look.size:
                go[look[~self._busy(w, look)]] = True
            go |= x >= 0.0
            lab.append(short)
            thr.append(np.where(~near | go, 1.0, -1.0))
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
        dx, dy, d = MirrorTeacher._from_conflict(w, look)
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
        from racecav.training.expert import YAW_RATE_GAIN

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

    @staticmethod
    def _stopped(w, look: np.ndarray) -> np.ndarray:
        """(len(look),) bool: a car in the ego's scan within APPROACH_M of the conflict point that
        has come to a stop (asked only for the families in both lists, whose cars start moving)."""
        stopped = (MirrorTeacher._from_conflict(w, look)[2] < APPROACH_M) & (w.v[look, 1:] < STOPPED_V)
        stopped &= w.seen_by_agent(look)
        return stopped.any(axis=1)

    def mirrored(self) -> np.ndarray:
        """(N,) bool: the worlds whose current episode is a scenario of a mirrored family and
        whose ego has an actor on its left within ``NEAR_M``. Before that the scene is about
        symmetric, and the policy's own label keeps one answer per scan (mirrored labels there
        would teach, e.g., the mirrored lane position for the same empty road). Relabel hold: the
        worlds of those families where no car has been seen yet (:meth:`_unseen`)."""
        if self.relabel == "hold":
            self._held = self._unseen()
            return self._held
        if self.relabel in ("stop", "yield"):
            self._held, self._stop_throttle = self._stop_and_look()
            if self.relabel == "yield" and self.anchor_families:  # their approach: tracking at full throttle
                unseen = self._unseen(self._anchored, self._seen_anchor)
                self._held, self._stop_throttle = self._held | unseen, np.where(unseen, 1.0, self._stop_throttle)
            return self._held
        return self._near(self._mirrored, +1.0)

    def in_families(self) -> np.ndarray:
        """(N,) bool: the worlds whose current episode runs a file of ``families``."""
        return self._family(self._mirrored)

    def steered(self) -> np.ndarray:
        """(N,) bool, relabel yield: the steps of the newest :meth:`mirrored` where the label
        steers round a car (:meth:`_dodge`), a few per cent of its labels; ``--bc-balance`` gives
        them half of each imitation minibatch (training/imitation_term.py). Other teachers: none."""
        return getattr(self, "_steered", np.zeros(self.fast.num_envs, bool)) & self._held

    def anchored(self) -> np.ndarray:
        """(N,) bool: the worlds of an anchor family whose ego has an actor near on its right
        (the mirror image of :meth:`mirrored`); their label is the policy's own action. With
        ``anchor_seen``, also the steps of a ``families`` scenario that :meth:`mirrored` (call it
        first, at the same step) did not hold. Relabel yield: the steps of its anchor families
        after their approach's label ended (a car seen, or the ego past the crossing's centre)."""
        if self.relabel == "yield":  # its anchor families, once their approach's label ended
            return self._family(self._anchored) & ~self._held
        near = self._near(self._anchored, -1.0)
        if self.anchor_seen:
            near |= self._family(self._mirrored) & ~self._held
        return near

    def _family(self, per_file: list[np.ndarray | None]) -> np.ndarray:
        """(N,) bool: the worlds whose current episode runs a file of ``per_file``."""
        return np.concatenate([np.zeros(w.n_envs, bool) if m is None else m[w.scenario_index]
                               for w, m in zip(self.fast.worlds, per_file)])

    def labels(self, raw_obs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(labels (N, 2), relabelled (N,)) for the raw (not normalised) stacked scans ``raw_obs``:
        on the :meth:`mirrored` steps the mirrored action (relabel mirror) or plain tracking of
        the ego's road at full throttle (relabel track or hold, training/expert.tracking_steer),
        or with the stop-and-look throttle (relabel stop)."""
        mask = self.mirrored()
        out = _acted(self.policy, raw_obs, self.coast_only)
        if self.anchor_policy is not None:
            anch = self.anchored()
            if anch.any():  # in its own view: its stack and stride may not be the run's
                ap, env = self.anchor_policy, self.fast
                own = getattr(ap, "obs_stack", env.n_stack), getattr(ap, "obs_stride", env.stride)
                view = raw_obs if own == (env.n_stack, env.stride) else env.stacked_view(*own)
                out[anch] = _acted(ap, view[anch], self.anchor_coast_only)
        if mask.any() and self.relabel == "mirror":
            m = mirror_scans(raw_obs[mask], self.policy.obs_stack)
            out[mask] = mirror_action(_acted(self.policy, m, self.coast_only))
        elif mask.any():
            from racecav.training.expert import tracking_steer

            steer = np.concatenate([tracking_steer(w) if w.actors is not None else np.zeros(w.n_envs)
                                    for w in self.fast.worlds])
            throttle = self._stop_throttle[mask] if self.relabel in ("stop", "yield") else np.ones(int(mask.sum()))
            if self.relabel in ("stop", "yield"):  # yield's own steer where it steers round a car
                steer = np.where(np.isnan(self._steer), steer, self._steer)
            out[mask] = np.stack([throttle, steer[mask]], axis=1)
        return out, mask


def _acted(policy, obs: np.ndarray, coast_only: bool) -> np.ndarray:
    """``policy``'s actions on ``obs`` as labels; ``coast_only``: a policy trained without a brake,
    whose a_T < 0 (a coast for it) is labelled 0 (a coast under the run's brake too)."""
    out = np.array(policy(obs), copy=True)
    if coast_only:
        out[:, 0] = np.maximum(out[:, 0], 0.0)
    return out


class MirroredPolicy:
    """``policy`` seen in a mirror: its action on the mirrored scans, mirrored (same view settings)."""

    def __init__(self, policy):
        self.policy = policy
        self.lidar, self.obs_stack = policy.lidar, policy.obs_stack
        self.obs_stride, self.brake_below = policy.obs_stride, policy.brake_below

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        return mirror_action(self.policy(mirror_scans(obs, self.obs_stack)))


class TeacherDriver:
    """The mirror teacher as a driver in the fast world: the policy's own action, and its mirrored
    action wherever :class:`MirrorTeacher` labels one (privileged: it reads the world's cars, so
    only fast-world evaluations can run it; select.eval_suite_fast calls :meth:`bind`)."""

    def __init__(self, policy, families: list[str], seen_only: bool):
        self.policy, self.families, self.seen_only = policy, families, seen_only
        self.teacher: MirrorTeacher | None = None

    def bind(self, fast_env) -> None:
        self.teacher = MirrorTeacher(self.policy, fast_env, self.families, seen_only=self.seen_only)

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        return self.teacher.labels(obs)[0]


def add_subcommands(sub) -> None:
    p = sub.add_parser("mirror", help="a policy and its mirror image (scans and steering reflected) on the "
                       "selection split: how asymmetric its skill is (training/mirror.py)")
    p.add_argument("--policy", default="avoid", help="shipped policy name, .npz, or a run's checkpoint .zip")
    p.add_argument("--trials", type=int, default=100, help="PyBullet trials per scenario (selection seeds)")
    p.add_argument("--suite-episodes", type=int, default=1024, help="fast-world episodes per suite (train split)")
    p.add_argument("--suite", default="conflicts", help="the conflict suite (name, folder or file) of the suite columns")
    p.add_argument("--paper-suite", default="paper-timed", help="the paper-timed suite (name, folder or file) of the last columns")
    p.add_argument("--mirror-families", default="cross-left", help="the families the teacher rows mirror "
                   "(comma-separated; the imitation term's --mirror-families)")
    p.add_argument("--out", type=Path, help="also write the table here (.md)")
    p.set_defaults(stage="mirror")


COLUMNS = [("right-to-left_success", "paper R-L"), ("head-to-head_success", "paper H-H"),
           ("left-to-right_success", "paper L-R"), ("conflict-right-to-left_success", "conflict R-L"),
           ("conflict-head-to-head_success", "conflict H-H"), ("conflict-left-to-right_success", "conflict L-R"),
           ("suite_success", "suite"), ("suite_cross-right", "suite cross-right"),
           ("suite_cross-left", "suite cross-left"), ("suite_braking", "suite braking"),
           ("suite_head-on", "suite head-on"), ("suite_staggered", "suite staggered"),
           ("suite_stopped", "suite stopped"), ("suite_turning", "suite turning"),
           ("paper-timed_cross-right", "paper-timed suite cross-right"),
           ("paper-timed_cross-left", "paper-timed suite cross-left"), ("paper-timed_head-on", "paper-timed suite head-on")]
"""(row key, column title) of the table."""


def mirror(args, cfg) -> int:
    """``racecav train mirror``: the table of a policy and its mirror image (and the references)."""
    import torch
    from tqdm import tqdm

    from racecav.common.bench import git_commit
    from racecav.common.config import EnvConfig
    from racecav.training.select import (eval_suite_fast, named_policy, policy_view_env, reference_drivers,
                                          selection_cells)

    torch.set_num_threads(1)
    if args.trials < 1 or args.suite_episodes < 1:
        raise SystemExit("racecav train mirror: --trials and --suite-episodes must be >= 1")
    policy = named_policy(args.policy)
    env = policy_view_env(policy, args.suite)
    # the imitation term's teachers as drivers: own action, mirrored once a car is near on the left in
    # a cross-left file (--mirror-seen: and in the scan); fast world only, they read the world's cars
    fams = [f.strip() for f in args.mirror_families.split(",") if f.strip()]
    teachers = {f"{args.policy} until a car is near on its left, then mirrored (`--expert mirror`)":
                TeacherDriver(policy, fams, seen_only=False),
                f"{args.policy} until a car is seen near on its left, then mirrored (`--expert mirror --mirror-seen`)":
                TeacherDriver(policy, fams, seen_only=True)}
    drivers = {f"{args.policy}": policy, f"{args.policy}, mirrored": MirroredPolicy(policy), **teachers,
               **{f"*{k}* (no evasion)": v for k, v in reference_drivers().items()}}
    rows = []
    for name, drv in tqdm(drivers.items(), desc="mirror", unit="driver"):
        denv = env if name in (args.policy, f"{args.policy}, mirrored", *teachers) else EnvConfig(scenarios=args.suite, scenario_share=1.0)
        try:
            row = (eval_suite_fast(drv, denv, args.suite_episodes) if name in teachers
                   else selection_cells(drv, denv, args.trials, args.suite_episodes, conflict=True))
            paper = eval_suite_fast(drv, denv.model_copy(update={"scenarios": args.paper_suite}), args.suite_episodes)
        except ValueError as e:  # a --mirror-families family the suites lack
            raise SystemExit(f"racecav train mirror: {e}") from None
        row.update({"paper-timed_" + k[len("suite_"):]: v for k, v in paper.items() if k.startswith("suite_")})
        rows.append({"driver": name, **row})
    suites = "" if (args.suite, args.paper_suite) == ("conflicts", "paper-timed") else f" --suite {args.suite} --paper-suite {args.paper_suite}"
    text = (f"`racecav train mirror --policy {args.policy} --trials {args.trials} --suite-episodes {args.suite_episodes}{suites}` "
            f"(commit {git_commit()}): success on the selection split, {args.trials} PyBullet trials per scenario "
            f"(selection seeds) and {args.suite_episodes} fast-world episodes per suite (train splits).\n\n"
            "| driver | " + " | ".join(t for _, t in COLUMNS) + " |\n|---|" + "---:|" * len(COLUMNS) + "\n")
    for r in rows:
        text += f"| {r['driver']} | " + " | ".join(
            f"{100 * r[k]:.0f} %" if k in r else "-" for k, _ in COLUMNS) + " |\n"
    print(text)
    if args.out:
        args.out.write_text(text)
        print(f"wrote {args.out}")
    return 0
