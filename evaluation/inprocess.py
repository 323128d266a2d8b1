"""In-process trials: one loop per backend, without the services.

Checkpoint selection (``racecav train select``), the training report, ``racecav train
references`` and ``racecav train paths`` run a driver here; ``racecav eval`` runs the same
scenarios through the real processes (evaluation/harness.py). A driver maps observations to
actions (a policy: common/policy.NumpyPolicy; or :class:`ConstantAction`).

- :func:`eval_scenario`: seeded PyBullet trials of one scenario (success as the sim decides it);
- :func:`eval_suite_fast`: one episode in each of N fast worlds of a suite's split;
- :func:`eval_env`: one traffic episode in each of N fast worlds (return, contacts, progress);
- :func:`reference_drivers`: the registry's two non-evading controllers as in-process drivers.
"""

from __future__ import annotations

from pathlib import Path

from racecav.common import registry

SELECT_SEED = 100_000
"""Selection seeds (SELECT_SEED + k): never the report's or the evaluation table's."""
REPORT_SEED = 0
"""Report seeds (REPORT_SEED + k) of the training report's PyBullet trials."""
HELDOUT_SEED = 900_000
"""Held-out seeds of the training env."""


def policy_view_env(policy, scenarios: str):
    """EnvConfig of scenario episodes only, seen as ``policy`` sees them: its metadata's view, scan
    stack and stride and brake (a driver without metadata: the paper's view)."""
    from racecav.common.config import EnvConfig

    md = getattr(policy, "metadata", {})
    return EnvConfig(scenarios=scenarios, scenario_share=1.0, lidar=md.get("lidar", "paper"),
                     obs_stack=policy.obs_stack, obs_stride=policy.obs_stride, brake_below=policy.brake_below)


def eval_env(policy, env_cfg, episodes: int, seed: int = HELDOUT_SEED) -> dict:
    """One episode in each of ``episodes`` fast worlds of the run's env (held-out seed)."""
    import numpy as np

    from racecav.training.vec_env import FastVecEnv

    env = FastVecEnv(n_envs=episodes, config=env_cfg, scenario_share=0.0, seed=seed)
    obs = env.reset()
    ret = np.zeros(episodes)
    done = np.zeros(episodes, bool)
    contact = np.zeros(episodes, bool)
    length = np.zeros(episodes)
    prog = np.zeros(episodes)
    fw = env.world
    lap = len(fw.cl) * fw.cl_ds
    sign = -1.0 if env_cfg.heading == "reversed" else 1.0

    def where():
        # the fast world's own centerline tracking (a local search): a global nearest point
        # would jump between the arms of a crossing (figure eight)
        return fw.cl_idx[:, 0] * fw.cl_ds

    s_prev = where()
    while not done.all():
        obs, r, d, infos = env.step(policy(obs))
        live = ~done
        ret[live] += r[live]
        length[live] += 1
        s = where()  # (after a reset of a done world: ignored, that world is no longer live)
        ds = (s - s_prev + lap / 2) % lap - lap / 2
        prog[live & ~d] += sign * ds[live & ~d]
        s_prev = s
        for i in np.flatnonzero(d & live):
            contact[i] = not infos[i].get("TimeLimit.truncated", False)
        done |= d
    return {"env_return": float(ret.mean()), "env_contact_rate": float(contact.mean()),
            "env_ep_len": float(length.mean()), "env_progress": float(prog.mean())}


def eval_suite_fast(policy, env_cfg, episodes: int, seed: int = SELECT_SEED) -> dict:
    """Success of one episode in each of ``episodes`` fast worlds running the run's scenario
    files (its suite's train split) with selection seeds: overall and per family.

    A run that trains on a pool of maps (``env.scenario_maps``) is measured on every source of its
    ``scenarios`` apart, an equal share of the episodes each, each episode on a map of its own:
    with the run's K maps the measure saw K maps (8 of a roads suite's 800) and called it the suite.
    Its families are then named ``source/family`` (two suites may both have a "braking")."""
    if not env_cfg.scenario_maps:
        return _suite_fast(policy, env_cfg, episodes, seed)
    parts = [p.strip() for p in str(env_cfg.scenarios).split(",") if p.strip()]
    out, ok = {}, 0.0
    for i, part in enumerate(parts):
        n = episodes // len(parts) + (1 if i < episodes % len(parts) else 0)
        if n == 0:
            continue
        # K = n: every episode on its own map (MapPool clamps K to the source's maps)
        r = _suite_fast(policy, env_cfg.model_copy(update={"scenarios": part, "scenario_maps": n}), n, seed)
        ok += r["suite_success"] * n
        prefix = f"{Path(part).name}/" if len(parts) > 1 else ""
        out.update({f"suite_{prefix}{k[6:]}": v for k, v in r.items()
                    if k.startswith("suite_") and k not in ("suite_success", "suite_episodes")})
    return {"suite_success": ok / max(1, episodes), "suite_episodes": int(episodes), **out}


def _suite_fast(policy, env_cfg, episodes: int, seed: int) -> dict:
    """One episode in each of ``episodes`` fast worlds of ``env_cfg``'s scenarios, as they draw them."""
    import numpy as np

    from racecav.training.vec_env import FastVecEnv

    # every file equally likely, whatever the run trained with (a curriculum is training only)
    env = FastVecEnv(n_envs=episodes, config=env_cfg.model_copy(update={"curriculum": False, "curriculum_boost": {}}),
                     scenario_share=1.0, seed=seed)
    if hasattr(policy, "bind"):  # a driver that reads the world's cars (a privileged teacher)
        policy.bind(env)
    obs = env.reset()
    names = np.concatenate([[w.scenarios[k].name for k in w.scenario_index] for w in env.worlds])
    done = np.zeros(env.num_envs, bool)
    success = np.zeros(env.num_envs, bool)
    while not done.all():
        obs, _r, d, infos = env.step(policy(obs))
        for i in np.flatnonzero(d & ~done):
            success[i] = infos[i].get("is_success", False)
        done |= d
    fams: dict[str, list[bool]] = {}
    for name, ok in zip(names, success):
        fams.setdefault(str(name).rsplit("-", 1)[0], []).append(bool(ok))
    out = {"suite_success": float(success.mean()), "suite_episodes": int(env.num_envs)}
    out.update({f"suite_{f}": float(np.mean(v)) for f, v in sorted(fams.items())})
    return out


def eval_scenario(policy, scenario: str, trials: int, seed0: int, record: int = 0) -> dict:
    """In-process PyBullet trials of one scenario (trial k: seed ``seed0 + k``): success,
    contact, progress.

    :param record: keep the ego and obstacle paths of the first ``record`` trials (key "paths").
    """
    from racecav.common.policy import ScanStack
    from racecav.common.vehicle import brake_from_action
    from racecav.sim.bullet_world import BulletWorld

    bw = BulletWorld(scenario, lidar=getattr(policy, "lidar", None))  # the policy's view
    dur = bw.scenario.duration_s
    ok = contact = 0
    prog, paths = [], []
    stack = ScanStack(getattr(policy, "obs_stack", 1), getattr(policy, "obs_stride", 1))
    try:
        for k in range(trials):
            obs = bw.reset(seed=seed0 + k)
            stack.reset()
            collided = False
            path = []
            while bw.t < dur - 1e-9 and not collided:
                a = policy(stack(obs[0]))
                obs, _, col, _ = bw.step(a, brake=brake_from_action(a[:1], getattr(policy, "brake_below", None)))
                collided = bool(col[0])
                if k < record:
                    path.append([*bw.agent_state()[0, :2], *[c for o in bw.obstacles()[0, :, :2] for c in o]])
            ok += bool(bw.success()[0])
            contact += collided
            prog.append(float(bw.progress()[0]))
            if k < record:
                paths.append({"xy": path, "success": bool(bw.success()[0]), "contact": collided})
    finally:
        bw.close()
    out = {"success": ok / trials, "contact": contact / trials,
           "progress": sum(prog) / len(prog), "trials": trials}
    if record:
        out["paths"] = paths
    return out


class ConstantAction:
    """A driver that never evades: the same action every step, whatever it sees."""

    lidar, obs_stack, obs_stride, brake_below = None, 1, 1, None  # the default (paper) view; it ignores it anyway

    def __init__(self, a_throttle: float):
        import numpy as np

        self.action = np.array([a_throttle, 0.0], np.float32)

    def __call__(self, obs):
        import numpy as np

        return np.broadcast_to(self.action, (*np.shape(obs)[:-1], 2)).copy()


def program_throttle(name: str) -> float:
    """The constant throttle of the registry's scripted controller ``name`` (its ``--program``
    a_T,a_delta,duration; HOLD: the throttle that holds registry.HOLD_SPEED, unrounded)."""
    from racecav.evaluation.harness import _hold_speed_throttle

    args = registry.CONTROLLERS[name].args
    program = args[args.index("--program") + 1]
    if program == "HOLD":
        return _hold_speed_throttle(registry.HOLD_SPEED)
    a_t, a_delta, _duration = (float(v) for v in program.split(","))
    if a_delta != 0.0:
        raise ValueError(f"controller {name}: steers ({program}); a reference drives straight")
    return a_t


def reference_drivers() -> dict[str, ConstantAction]:
    """The non-evading references, in-process: the registry's ``scripted`` (straight at the
    throttle that holds HOLD_SPEED, the scenarios' ego start speed) and ``full-throttle``
    controllers (straight at full throttle, about the policies' speed)."""
    return {f"straight {registry.HOLD_SPEED:g} m/s": ConstantAction(program_throttle("scripted")),
            "straight, full throttle": ConstantAction(program_throttle("full-throttle"))}
