"""``racecav train dagger``: the policy imitates the yield teacher (DAgger), resumable.

    racecav train dagger --run-dir runs/avoid-yield-nobalance64 \\
        --init-from training/checkpoints/avoid-yield-turn64/checkpoints/step_001007616.zip ...

(the shipped avoid's recipe: docs/training.md, row 95). PPO learns the conflicts slowly: a
success or a contact seconds later is its only signal about which of two similar scenes needed an
evasion. Here a teacher that reads the world's state (training/teacher.YieldTeacher) labels every
step, and the policy (the same SB3 MlpPolicy, 2 x 64 tanh, on the same lidar observation) is
fitted to those labels by regression of its mean action (Ross et al. 2011, DAgger): the policy
drives (``expert_share`` of the episodes are driven by the teacher), so the labels cover the
states the policy itself reaches; all labelled steps are aggregated (the newest ``dataset_max``)
and fitted after each rollout. With ``--bc-balance`` half of each minibatch are the steps where
the teacher steers round a car (YieldTeacher.steered; then counted as "manoeuvres"), a few per
cent of its labels (rows 92-94 of docs/training.md). The shipped avoid (row 95) is fitted
uniformly: balanced, the policy also steered round the turning family's oncoming car, which the
teacher waits for.

The run folder is a PPO run's (training/train.py): config.json, progress.csv, checkpoints/
step_<N>.zip + .vecnorm.pkl, latest.*; ``racecav train select`` and ``ship`` read it as they read
a PPO run. The observation normalisation is the ``--init-from`` policy's, frozen (the policy
keeps the input scale it was trained on). The value head and action std are kept as loaded,
so a PPO run can continue from a checkpoint (``racecav train overtake --init-from``).
progress.csv's columns: the imitation loss, the share of steps on which the policy's steering
is within 0.05 rad of the teacher's, the success rate of the scenario episodes the policy drove
and the share of its traffic episodes that ended in a contact, and the share of labels that are
relabelled by the teacher (with --bc-balance: its steers round a car).
"""

from __future__ import annotations

import logging
import os
import signal
import time
from pathlib import Path

import numpy as np

from racecav.training.runs import append_csv, save_checkpoint, source_env, truncate_csv

log = logging.getLogger("racecav.train")

FIELDS = ["timesteps", "wall_s", "samples_per_s", "loss", "steer_agree", "scenario_success",
          "traffic_contacts", "episodes", "dataset", "manoeuvres"]
STEER_TOL = 0.05  # rad: "agrees with the teacher" in progress.csv
LOSS_SCALE = (0.5, 0.15)  # throttle, steering: the loss counts steering errors of 0.15 like 0.5 of throttle


def action_bounds(car, brake_below: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) of the actions that still change the car's command: a_T beyond [0, 1] and a_delta
    beyond the steering range are clipped by the actuation (common/vehicle.py). With a brake
    (``brake_below``) a_T below 0 still matters (below brake_below the car brakes): a_T's bound is
    then -1, the action space's, or a brake label would be clipped to a coast."""
    return (np.array([0.0 if brake_below is None else -1.0, car.delta_min / car.steer_gain], np.float32),
            np.array([1.0, car.delta_max / car.steer_gain], np.float32))


def mean_action(policy, obs):
    """The SB3 policy's mean action (torch, (B, 2)) on normalised observations ``obs``."""
    import torch

    feats = policy.extract_features(torch.as_tensor(obs), policy.pi_features_extractor)
    return policy.action_net(policy.mlp_extractor.forward_actor(feats))


def imitation_loss(pred, label, lo, hi, scale):
    """Squared error of the policy's mean action ``pred`` against the teacher's ``label`` (torch,
    (B, 2)), zero where both lie at or beyond the same bound (the car does the same)."""
    import torch

    diff = pred - label
    diff = torch.where(label >= hi - 1e-6, torch.clamp(diff, max=0.0), diff)
    diff = torch.where(label <= lo + 1e-6, torch.clamp(diff, min=0.0), diff)
    return ((diff / scale) ** 2).mean()


def minibatches(rng: np.random.Generator, man: np.ndarray, size: int, balance: bool, count: int):
    """``count`` index arrays of ``size`` into the stored labels (``man``: the steps of the kind that
    gets its own half): uniform, or with ``balance`` half ``man`` steps and half the others
    (``--bc-balance``; uniform while either kind is missing). The split is made once per fit."""
    mine, rest = (np.flatnonzero(man), np.flatnonzero(~man)) if balance else ((), ())
    half = size // 2
    for _ in range(count):
        if len(mine) and len(rest):
            yield np.concatenate([mine[rng.integers(0, len(mine), half)], rest[rng.integers(0, len(rest), size - half)]])
        else:
            yield rng.integers(0, len(man), size)


def make_teacher(tc, fast):
    """The run's teacher over the VecEnv's worlds (``tc.expert``)."""
    if tc.expert == "predictive":
        from racecav.training.predictive_teacher import PredictiveTeacher

        if any(w.actors is None for w in fast.worlds):
            raise ValueError("--expert predictive labels scenario episodes only: set --env-scenario-share 1")
        return PredictiveTeacher(fast.worlds)
    return yield_teacher(tc, fast)


def teacher_labels(teacher, tc, venv) -> tuple[np.ndarray, np.ndarray]:
    """(labels (N, 2), the steps of the kind --bc-balance gives half of each minibatch)."""
    if tc.expert == "predictive":  # its manoeuvres round a car
        return teacher.labels(), teacher.steered()
    label, man = teacher.labels(venv.get_original_obs())
    return label, (teacher.steered() if tc.bc_balance else man)


def yield_teacher(tc, fast):
    """The frozen ``init_from`` policy (with its normalisation) under the run's view settings,
    relabelled by yield in the ``mirror_families`` scenarios (training/teacher.py)."""
    from racecav.training.policy_io import policy_from_checkpoint
    from racecav.training.teacher import YieldTeacher

    env = tc.env
    policy = policy_from_checkpoint(Path(tc.init_from), env.obs_stack, env.brake_below, env.lidar, env.obs_stride)
    if policy.obs_dim != fast.observation_space.shape[0]:
        raise ValueError(f"--expert {tc.expert}: {tc.init_from} takes {policy.obs_dim} inputs, the env gives "
                         f"{fast.observation_space.shape[0]} (the teacher must see the run's view)")
    families = [f.strip() for f in tc.mirror_families.split(",") if f.strip()]
    return YieldTeacher(policy, fast, families,
                        teacher_brakes=source_env(Path(tc.init_from), "brake_below", None) is not None)


DATASET = "dagger-state.pt"
"""Beside latest.*: the aggregate (oldest first), the optimiser and the rng of the last checkpoint.
Without it a resumed stage started from an empty aggregate and fitted the policy to its first few
rollouts alone: a stage run in chunks was not the stage run at once."""


def save_state(run_dir: Path, samples: int, obs, act, man, size: int, head: int, opt, rng) -> None:
    """Write the DAgger state of ``samples`` (renamed into place: never half a file)."""
    import torch

    order = np.r_[head:size, 0:head] if size == len(obs) else np.arange(size)  # oldest first
    tmp = run_dir / (DATASET + ".tmp")
    torch.save({"timesteps": int(samples), "obs": torch.from_numpy(obs[order]), "act": torch.from_numpy(act[order]),
                "man": torch.from_numpy(man[order]), "opt": opt.state_dict(), "rng": rng.bit_generator.state}, tmp)
    os.replace(tmp, run_dir / DATASET)


def load_state(run_dir: Path, samples: int, dim: int) -> dict | None:
    """The saved DAgger state if it is the checkpoint's being resumed (same sample count and
    observation size); otherwise None, logged (e.g. a stage resumed from its committed record)."""
    import torch

    path = run_dir / DATASET
    if samples == 0:
        return None
    if not path.is_file():
        log.warning("%s: no %s: the aggregate starts empty", run_dir, DATASET)
        return None
    st = torch.load(path, weights_only=False)
    if st["timesteps"] != samples or st["obs"].shape[1] != dim:
        log.warning("%s: %s is of %d samples, not the checkpoint's %d: the aggregate starts empty",
                    run_dir, DATASET, st["timesteps"], samples)
        return None
    return st


class _Stop:
    requested = False

    def __call__(self, signum, frame):
        log.warning("signal %d: checkpoint and stop", signum)
        self.requested = True


def imitate(model, venv, tc, run_dir: Path, state: dict, total: int, progress: bool = True) -> int:
    """The DAgger loop until ``total`` samples or a signal: rollouts, labels, fits, checkpoints.

    :param model: the SB3 PPO model whose policy is fitted (its value head is left alone).
    :param venv: VecNormalize over a FastVecEnv, statistics frozen here.
    :param tc: the run's TrainConfig; ``state``: latest.json's timesteps and wall_s.
    """
    import torch
    from tqdm import tqdm

    fast = venv.venv
    venv.training = False  # frozen statistics
    policy = model.policy
    teacher = make_teacher(tc, fast)
    params = list(policy.mlp_extractor.policy_net.parameters()) + list(policy.action_net.parameters())
    opt = torch.optim.Adam(params, lr=tc.learning_rate)
    scale = torch.tensor(LOSS_SCALE, dtype=torch.float32)
    lo, hi = action_bounds(fast.world.car, tc.env.brake_below)
    lo_t, hi_t = torch.as_tensor(lo), torch.as_tensor(hi)
    rng = np.random.default_rng(tc.seed + state["timesteps"])
    n, dim = fast.num_envs, fast.observation_space.shape[0]
    cap = tc.dataset_max
    data_obs = np.zeros((cap, dim), np.float32)
    data_act = np.zeros((cap, 2), np.float32)
    data_man = np.zeros(cap, bool)  # relabelled by the teacher (with bc_balance: a steer round a car)
    size = head = 0
    samples, wall0, t0 = int(state["timesteps"]), float(state["wall_s"]), time.monotonic()
    saved = load_state(run_dir, samples, dim)
    if saved is not None:  # the newest ``cap`` of the saved aggregate, oldest first
        size = min(len(saved["obs"]), cap)
        data_obs[:size], data_act[:size], data_man[:size] = (saved[k][-size:].numpy() for k in ("obs", "act", "man"))
        head = size % cap
        opt.load_state_dict(saved["opt"])
        rng.bit_generator.state = saved["rng"]
        log.info("%s: resumed the aggregate (%d samples)", run_dir, size)
        del saved
    next_ckpt = (samples // tc.checkpoint_every + 1) * tc.checkpoint_every
    stop = _Stop()
    old = {sig: signal.signal(sig, stop) for sig in (signal.SIGTERM, signal.SIGINT)}
    bar = tqdm(total=total, initial=samples, unit="sa", unit_scale=True, mininterval=2.0,
               dynamic_ncols=True, desc=run_dir.name) if progress else None

    def save(final: bool) -> None:
        model.num_timesteps = samples
        save_state(run_dir, samples, data_obs, data_act, data_man, size, head, opt, rng)
        save_checkpoint(run_dir, model, venv, wall0 + time.monotonic() - t0, final)

    truncate_csv(run_dir / "progress.csv", samples, FIELDS)
    obs = venv.reset()
    by_expert = rng.random(n) < tc.expert_share  # who drives each world's episode
    rollouts = 0
    try:
        while samples < total and not stop.requested:
            t_roll = time.monotonic()
            agree = succ = eps_s = contacts = eps_t = done_steps = 0
            for _ in range(tc.n_steps):
                label, man = teacher_labels(teacher, tc, venv)
                # as the car acts (a policy teacher's steering saturates beyond the range): the
                # loss and the agreement then read a label beyond a bound as that bound
                label = np.clip(label, lo, hi)
                with torch.no_grad():
                    student = mean_action(policy, obs).numpy()
                steer = np.clip(student[:, 1], lo[1], hi[1]) * fast.world.car.steer_gain
                agree += int((np.abs(steer - label[:, 1] * fast.world.car.steer_gain) < STEER_TOL).sum())
                k = np.arange(head, head + n) % cap
                data_obs[k], data_act[k], data_man[k] = obs, label, man
                head, size = (head + n) % cap, min(size + n, cap)
                act = np.where(by_expert[:, None], label, np.clip(student, -1, 1))
                obs, _, dones, infos = venv.step(act)
                for i in np.flatnonzero(dones & ~by_expert):  # the policy's own episodes
                    if fast.is_scenario[i]:
                        eps_s += 1
                        succ += bool(infos[i].get("is_success"))
                    else:
                        eps_t += 1
                        contacts += not infos[i].get("TimeLimit.truncated", False)
                by_expert[dones] = rng.random(int(dones.sum())) < tc.expert_share
                samples += n
                done_steps += 1
                if bar is not None:
                    bar.update(n)
                if stop.requested:
                    break
            losses = []
            for j in minibatches(rng, data_man[:size], tc.batch_size, tc.bc_balance, tc.grad_steps):
                pred = mean_action(policy, data_obs[j])
                loss = imitation_loss(pred, torch.as_tensor(data_act[j]), lo_t, hi_t, scale)
                opt.zero_grad()
                loss.backward()
                opt.step()
                losses.append(float(loss.detach()))
            dt = time.monotonic() - t_roll
            row = {"timesteps": samples, "wall_s": round(wall0 + time.monotonic() - t0, 2),
                   "samples_per_s": round(done_steps * n / dt, 1), "loss": round(float(np.mean(losses)), 5),
                   "steer_agree": round(agree / (done_steps * n), 4),
                   "scenario_success": round(succ / eps_s, 4) if eps_s else "",
                   "traffic_contacts": round(contacts / eps_t, 4) if eps_t else "",
                   "episodes": eps_s + eps_t, "dataset": size, "manoeuvres": round(float(data_man[:size].mean()), 4)}
            append_csv(run_dir / "progress.csv", FIELDS, row)
            if bar is not None:
                bar.set_postfix_str(f"loss {row['loss']:.3f} agree {row['steer_agree']:.2f} "
                                    f"success {row['scenario_success']}", refresh=False)
            if samples >= next_ckpt:
                save(final=False)
                next_ckpt = (samples // tc.checkpoint_every + 1) * tc.checkpoint_every
            rollouts += 1
            if tc.map_resample_every and rollouts % tc.map_resample_every == 0 and not stop.requested:
                fast.resample_maps()  # other roads; their episodes start afresh
                teacher = make_teacher(tc, fast)
                obs = venv.reset()
                by_expert = rng.random(n) < tc.expert_share
    finally:
        for sig, h in old.items():
            signal.signal(sig, h)
        if bar is not None:
            bar.close()
    save(final=not stop.requested)
    log.info("%s at %d samples (%s)", run_dir, samples, "stopped by signal" if stop.requested else "done")
    return 0

