"""``racecav train select|references|ship|report``: checkpoint evaluation, shipping and the results page.

- ``select --run-dir DIR``: every checkpoint (or the last ``--last K``) of a run is evaluated on
  held-out seeds of its own training env (fast world: mean return, contact rate) and on the three
  intersection scenarios in-process on the PyBullet backend (success = no contact and ego
  progress >= the scenario's min_progress_m). Writes ``DIR/eval.csv`` and ``DIR/eval.png`` and
  names the best: highest mean intersection success in 5-point steps (finer differences are noise
  at 30 trials per scenario), then the highest held-out return, then fewer intersection contacts
  (the paper picked its checkpoints by evaluation too). Selection seeds (SELECT_SEED + k) differ from
  the report's (REPORT_SEED + k), so the reported rates are not the ones the pick was made on.
- ``ship --run-dir DIR --checkpoint best|latest|STEP --name racing|default|reversed``: writes
  common/data/policies/NAME.{npz,json,zip,vecnorm.pkl} and copies the run's learning curve,
  settings and evaluation to training/checkpoints/RUN/ (committed: the report and ``--resume``
  across sessions need them); ``select`` saves that record too, for runs that are not shipped.
- ``references``: the non-evading references (straight at 1 m/s and at full throttle) scored on
  the same selection split as an avoidance run's checkpoints -> training/checkpoints/references.csv,
  the ablation table's reference rows.
- ``report``: >= 100 trials per scenario for each shipped policy, learning curves, throughput,
  wall time -> docs/training.md (+ docs/img/training_*.png); results also go into the policies'
  JSON metadata.
"""

from __future__ import annotations

import csv
import json
import logging
import math
import shutil
import time
from pathlib import Path

from racecav.common import registry
from racecav.common.lidar import VIEWS
from racecav.training import targets
from racecav.training.runs import load_run_config, run_dir_of

log = logging.getLogger("racecav.train")

SCENARIOS = registry.PAPER_SCENARIOS
CONFLICT_SCENARIOS = registry.CONFLICT_SCENARIOS
SELECT_SEED = 100_000
REPORT_SEED = 0
SUCCESS_RESOLUTION = 0.05
HELDOUT_SEED = 900_000
REPO = Path(__file__).resolve().parent.parent
COMMITTED = REPO / "training" / "checkpoints"
PAPER_HW = {k.removeprefix("drl-"): tuple(round(100 * v) for v in r) for k, r in registry.PAPER_TABLE1.items()}


def add_subcommands(sub) -> None:
    p = sub.add_parser("select", help="evaluate a run's checkpoints (held-out env seeds + PyBullet intersection scenarios), pick the best")
    p.add_argument("--run-dir", type=Path, required=True)
    p.add_argument("--trials", type=int, default=30, help="PyBullet trials per scenario and checkpoint")
    p.add_argument("--episodes", type=int, default=64, help="held-out episodes in the training env")
    p.add_argument("--last", type=int, help="only the last K checkpoints")
    p.add_argument("--every", type=int, default=1, help="every k-th checkpoint, counted back from the newest "
                   "(which is always evaluated)")
    p.add_argument("--newest-first", action="store_true", help="evaluate the newest checkpoints first (a run "
                   "still training: its new checkpoints need not wait for the old ones)")
    p.add_argument("--no-progress", action="store_true", help="no tqdm bar")
    p.add_argument("--no-intersection", action="store_true", help="held-out env only (racing stage)")
    p.add_argument("--no-record", action="store_true", help="do not copy the run's records to "
                   "training/checkpoints/<run>/ (a scratch evaluation, e.g. a folder holding one checkpoint)")
    p.add_argument("--suite-episodes", type=int, default=512, help="runs with --scenarios: fast-world episodes "
                   "on the suite's train split (selection seeds) per checkpoint")
    p.add_argument("--free-suite", default="open", help="runs with --scenarios: a suite of free roads (NAME or DIR; "
                   "`racecav suite generate --name open`) whose train split gives the free_success column, half "
                   "as many episodes (not in the score; skipped with a warning if not generated; '' for none)")
    p.set_defaults(stage="select")
    p = sub.add_parser("references", help="the non-evading references (straight at 1 m/s, at full throttle) "
                       "on select's selection split -> training/checkpoints/references.csv (the ablation's reference rows)")
    p.add_argument("--trials", type=int, default=100, help="PyBullet trials per scenario")
    p.add_argument("--suite-episodes", type=int, default=512, help="fast-world episodes on the suite's train split")
    p.add_argument("--suite", default="conflicts", help="the conflict suite the avoidance runs are selected on")
    p.add_argument("--free-suite", default="open", help="the free-road suite of the free_success column ('' for none)")
    p.add_argument("--out", type=Path, default=REFERENCES_CSV)
    p.set_defaults(stage="references")
    p = sub.add_parser("ship", help="export a checkpoint as common/data/policies/NAME.{npz,json,zip}")
    p.add_argument("--run-dir", type=Path, required=True)
    p.add_argument("--checkpoint", default="best", help="best (from eval.csv) | latest | STEP")
    p.add_argument("--name", required=True, help="racing | default | reversed (or any file name)")
    p.set_defaults(stage="ship")
    p = sub.add_parser("paths", help="draw a policy's paths through the intersection scenarios (PyBullet, "
                       "selection seeds): where it turns, and which way")
    p.add_argument("--policy", required=True, help="shipped policy name, .npz, or a run's checkpoint .zip")
    p.add_argument("--scenarios", default="right-to-left,conflict-right-to-left,left-to-right,conflict-left-to-right",
                   help="comma-separated intersection scenarios (common/data/scenarios)")
    p.add_argument("--trials", type=int, default=20, help="trials drawn per scenario")
    p.add_argument("--out", type=Path, required=True, help="the figure (.png)")
    p.set_defaults(stage="paths")
    p = sub.add_parser("report", help="evaluate the shipped policies (>= 100 PyBullet trials per scenario) -> docs/training.md")
    p.add_argument("--trials", type=int, default=100)
    p.add_argument("--policies", default="racing,default,reversed,avoid")
    p.add_argument("--reuse", action="store_true", help="reuse the evaluation stored in the metadata")
    p.set_defaults(stage="report")


def run(args, cfg) -> int:
    return {"select": select, "references": references, "ship": ship, "report": report,
            "paths": draw_paths}[args.train_cmd](args, cfg)


# ----------------------------------------------------------------------------------- evaluation
def policy_from_checkpoint(zip_path: Path, obs_stack: int = 1, brake_below: float | None = None,
                           lidar: str = "paper", obs_stride: int = 1):
    """NumpyPolicy of an SB3 checkpoint (+ its ``.vecnorm.pkl`` normalisation if present); the
    arguments are the run's env settings its metadata records (EnvConfig)."""
    import pickle

    from stable_baselines3 import PPO

    from racecav.common.policy import NumpyPolicy, policy_arrays_from_sb3

    model = PPO.load(zip_path, device="cpu")
    arrays = policy_arrays_from_sb3(model)
    vn = zip_path.with_suffix(".vecnorm.pkl")
    if vn.is_file():
        with vn.open("rb") as f:
            norm = pickle.load(f)
        n_in = arrays["w0"].shape[0]  # the actor's inputs (a privileged critic reads more)
        arrays.update(obs_mean=norm.obs_rms.mean[:n_in], obs_var=norm.obs_rms.var[:n_in],
                      obs_clip=norm.clip_obs, obs_eps=norm.epsilon)
    return NumpyPolicy(arrays, {"obs_stack": obs_stack, "obs_stride": obs_stride, "brake_below": brake_below,
                                "lidar": lidar})


def checkpoint_policy(zip_path: Path):
    """NumpyPolicy of a run's checkpoint (``<run>/checkpoints/step_N.zip`` or ``<run>/latest.zip``)
    with the env settings of the run's config.json (its view, stack, stride and brake)."""
    zip_path = Path(zip_path)
    if not zip_path.is_file():
        raise FileNotFoundError(f"checkpoint {zip_path}: no such file")
    run_dir = run_dir_of(zip_path)
    if not (run_dir / "config.json").is_file():
        raise FileNotFoundError(f"checkpoint {zip_path}: no run record {run_dir / 'config.json'} (its env settings)")
    env = load_run_config(run_dir)[0].env
    return policy_from_checkpoint(zip_path, env.obs_stack, env.brake_below, env.lidar, env.obs_stride)


def named_policy(spec: str):
    """A shipped policy's name or an .npz (common/policy.load_policy), or a run's checkpoint .zip
    with its run's settings (checkpoint_policy): the ``--policy`` of probe and mirror."""
    from racecav.common.policy import load_policy

    return checkpoint_policy(Path(spec)) if spec.endswith(".zip") else load_policy(spec)


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
    files (its suite's train split) with selection seeds: overall and per family."""
    import numpy as np

    from racecav.training.vec_env import FastVecEnv

    # every file equally likely, whatever the run trained with (a curriculum is training only)
    env = FastVecEnv(n_envs=episodes, config=env_cfg.model_copy(update={"curriculum": False, "curriculum_boost": {}}),
                     scenario_share=1.0, seed=seed)
    if hasattr(policy, "bind"):  # a driver that reads the world's cars (privileged: training/mirror.TeacherDriver)
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
    """In-process PyBullet trials of one intersection scenario: success, contact, progress.

    :param record: keep the ego and obstacle paths of the first ``record`` trials (key "paths").
    """
    from racecav.sim.bullet_world import BulletWorld

    from racecav.common.policy import ScanStack
    from racecav.common.vehicle import brake_from_action

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


def selection_cells(policy, env_cfg, trials: int, suite_episodes: int, conflict: bool,
                    free_suite: str | None = None) -> dict:
    """A policy on the selection split: the paper-timed scenarios (success, contact, progress) and,
    for an avoidance run (``conflict``), the conflict-timed scenarios, the conflict suite's train
    split in the fast world, and the score (mean of suite, conflict-timed and paper-timed success);
    with ``free_suite`` (a generated suite of free roads, e.g. ``open``) also ``free_success``, its
    train split in the fast world: a policy that evades where nothing is there fails it. Not in the
    score (the rows before it have no such column)."""
    row, rates = {}, []
    for sc in SCENARIOS:
        r = eval_scenario(policy, sc, trials, SELECT_SEED)
        row.update({f"{sc}_success": r["success"], f"{sc}_contact": r["contact"],
                    f"{sc}_progress": round(r["progress"], 3)})
        rates.append(r["success"])
    row["intersection_success"] = sum(rates) / len(rates)
    row["trials"] = trials
    if conflict:
        crates = [eval_scenario(policy, sc, trials, SELECT_SEED)["success"] for sc in CONFLICT_SCENARIOS]
        row.update({f"{sc}_success": r for sc, r in zip(CONFLICT_SCENARIOS, crates)})
        row["conflict_success"] = sum(crates) / len(crates)
        # the first scenario source is the conflict suite (the whole of it, if training used a
        # seen-filtered cut); any others (e.g. clock-timed traffic, which a non-evading car may
        # pass) are only training mix
        from racecav.common.scenario import unfiltered

        sel_env = env_cfg.model_copy(update={"scenarios": unfiltered(env_cfg.scenarios.split(",")[0].strip())})
        row.update(eval_suite_fast(policy, sel_env, suite_episodes))
        row["score"] = (row["suite_success"] + row["conflict_success"] + row["intersection_success"]) / 3
        if free_suite:
            row["free_success"] = free_success(policy, env_cfg, free_suite, suite_episodes)
    return row


def free_success(policy, env_cfg, free_suite: str, suite_episodes: int) -> float:
    """Success on the free-road suite's train split (fast world, selection seeds, half as many
    episodes as the conflict suite's: one family)."""
    free_env = env_cfg.model_copy(update={"scenarios": free_suite})
    return eval_suite_fast(policy, free_env, max(1, suite_episodes // 2))["suite_success"]


def free_suite_or_none(spec: str | None) -> str | None:
    """``spec`` if that suite is generated, else None with a warning (the column is skipped)."""
    if not spec:
        return None
    from racecav.common.scenario import open_suite

    try:
        open_suite(spec)
    except (FileNotFoundError, ValueError) as e:
        log.warning("free-road column skipped (%s); the open suite is generated by racecav suite generate "
                    "--name open --n 20 --n-train 200 --seed 3 (docs/world.md)", e)
        return None
    return spec


class ConstantAction:
    """A driver that never evades: the same action every step, whatever it sees (the trivial
    references, as the scripted controllers of ``racecav eval``)."""

    lidar, obs_stack, obs_stride, brake_below = None, 1, 1, None  # the default (paper) view; it ignores it anyway

    def __init__(self, a_throttle: float):
        import numpy as np

        self.action = np.array([a_throttle, 0.0], np.float32)

    def __call__(self, obs):
        import numpy as np

        return np.broadcast_to(self.action, (*np.shape(obs)[:-1], 2)).copy()


def reference_drivers() -> dict[str, ConstantAction]:
    """The non-evading references: straight at the throttle that holds registry.HOLD_SPEED (the
    scenarios' ego start speed) and straight at full throttle (about the policies' speed)."""
    from racecav.common.vehicle import load_car, throttle_for_speed

    car = load_car()
    hold = float(throttle_for_speed(registry.HOLD_SPEED, car, car.agent_speed_scale))
    return {f"straight {registry.HOLD_SPEED:g} m/s": ConstantAction(hold), "straight, full throttle": ConstantAction(1.0)}


REFERENCES_CSV = COMMITTED / "references.csv"
"""The references on the selection split (``racecav train references``), beside the ablation."""


def references(args, cfg) -> int:
    """The non-evading references scored like a checkpoint of an avoidance run: the selection
    split's cells and score, so the ablation's rows have their trivial references on the same seeds."""
    from tqdm import tqdm

    from racecav.common.config import EnvConfig

    env_cfg = EnvConfig(scenarios=args.suite, scenario_share=1.0)
    rows = []
    for name, drv in tqdm(reference_drivers().items(), desc="references", unit="driver"):
        rows.append({"reference": name, "a_throttle": float(drv.action[0]),
                     **selection_cells(drv, env_cfg, args.trials, args.suite_episodes, conflict=True,
                                       free_suite=free_suite_or_none(args.free_suite))})
        log.info("%s: score %.3f", name, rows[-1]["score"])
    fields = list(dict.fromkeys(k for r in rows for k in r))
    _write_csv(args.out, fields, rows)
    print(f"wrote {args.out}")
    return 0


def _checkpoints(run_dir: Path) -> list[Path]:
    return sorted((run_dir / "checkpoints").glob("step_*.zip"))


def _step(path: Path) -> int:
    return int(path.stem.split("_")[1])


def select(args, cfg) -> int:
    import torch
    from tqdm import tqdm

    torch.set_num_threads(1)
    run_dir = args.run_dir
    tc, _record = load_run_config(run_dir)
    cks = _checkpoints(run_dir)
    if not cks:
        log.error("no checkpoints in %s", run_dir / "checkpoints")
        return 2
    picked = cks[::-1][::max(1, args.every)][::-1]
    if args.last:
        picked = picked[-args.last:]
    out = run_dir / "eval.csv"
    done = {}
    if out.is_file():  # resumable: keep rows already evaluated with the same trial count
        with out.open() as f:
            done = {int(r["timesteps"]): r for r in csv.DictReader(f)}
    fields = ["timesteps", "checkpoint", "env_return", "env_contact_rate", "env_ep_len", "env_progress"]
    conflict = bool(tc.env.scenarios)
    free = free_suite_or_none(args.free_suite) if conflict and not args.no_intersection else None
    if not args.no_intersection:
        fields += [f"{s}_{m}" for s in SCENARIOS for m in ("success", "contact", "progress")]
        fields += ["intersection_success", "trials"]
        if conflict:  # avoidance runs: the suite's train split and the conflict-timed paper scenarios
            fields += [f"{s}_success" for s in CONFLICT_SCENARIOS] + ["conflict_success", "suite_success",
                                                                       "suite_episodes", "score", "free_success"]
            # the per-family columns of rows already evaluated: a run that evaluates nothing new
            # must not drop them
            fields += sorted({k for r in done.values() for k in r if k.startswith("suite_") and k not in fields})
    rows = []
    for ck in tqdm(picked[::-1] if args.newest_first else picked, desc=f"select {run_dir.name}", unit="ckpt",
                   disable=args.no_progress):
        n = _step(ck)
        prev = done.get(n)
        if prev and (args.no_intersection or int(prev.get("trials") or 0) == args.trials):
            if free and prev.get("free_success") in (None, ""):  # evaluated before the column: add it alone
                pol = policy_from_checkpoint(ck, tc.env.obs_stack, tc.env.brake_below, tc.env.lidar, tc.env.obs_stride)
                prev = {**prev, "free_success": free_success(pol, tc.env, free, args.suite_episodes)}
                log.info("%s: free_success %.3f added", ck.name, prev["free_success"])
            rows.append(prev)
            continue
        pol = policy_from_checkpoint(ck, tc.env.obs_stack, tc.env.brake_below, tc.env.lidar, tc.env.obs_stride)
        row = {"timesteps": n, "checkpoint": ck.name, **eval_env(pol, tc.env, args.episodes)}
        if not args.no_intersection:
            row.update(selection_cells(pol, tc.env, args.trials, args.suite_episodes, conflict, free))
            fields += [k for k in row if k.startswith("suite_") and k not in fields]
        rows.append(row)
        seen = {int(r["timesteps"]) for r in rows}
        _write_csv(out, fields, sorted(rows + [r for n, r in done.items() if n not in seen],
                                       key=lambda r: int(r["timesteps"])))
        log.info("%s: %s", ck.name, {k: row.get(k) for k in fields[2:]})
    seen = {int(r["timesteps"]) for r in rows}
    rows += [r for n, r in done.items() if n not in seen]  # keep earlier evaluations
    rows.sort(key=lambda r: int(r["timesteps"]))
    _write_csv(out, fields, rows)
    best = pick_best(rows, not args.no_intersection)
    (run_dir / "best.json").write_text(json.dumps(best, indent=2, default=str) + "\n")
    _plot_eval(rows, run_dir / "eval.png", run_dir.name, not args.no_intersection)
    if args.no_record:
        log.info("--no-record: %s stays out of %s", run_dir, COMMITTED)
    else:  # curves, evaluation and latest checkpoint: for the report and --resume
        dst = save_run_record(run_dir)
        log.info("records of %s copied to %s (committed; --no-record for a scratch folder)", run_dir, dst)
    print(f"best checkpoint of {run_dir}: {best['checkpoint']} ({_fmt_row(best)})")
    return 0


def _shown(value) -> str:
    """A setting as the ablation's change column prints it (an empty string would print as nothing)."""
    return repr(value) if value == "" else str(value)


def pick_best(rows: list[dict], intersection: bool) -> dict:
    """Highest mean intersection success in steps of SUCCESS_RESOLUTION (smaller differences are
    noise at 30 trials per scenario), then the highest held-out return in the training env, then
    fewest intersection contacts (racing: return only)."""
    def key(r):
        if not intersection:
            return (0.0, float(r["env_return"]), 0.0)
        if r.get("score") not in (None, ""):  # avoidance runs: suite, conflict-timed and paper scenarios
            return (math.floor(float(r["score"]) / SUCCESS_RESOLUTION + 1e-9), float(r["suite_success"]),
                    float(r["env_return"]))
        no_contact = sum(1 - float(r[f"{s}_contact"]) for s in SCENARIOS) / len(SCENARIOS)
        succ = math.floor(float(r["intersection_success"]) / SUCCESS_RESOLUTION + 1e-9)
        return (succ, float(r["env_return"]), no_contact)
    return max(rows, key=key)


def _fmt_row(r: dict) -> str:
    parts = [f"env return {float(r['env_return']):.0f}, contact {100 * float(r['env_contact_rate']):.0f} %"]
    if "intersection_success" in r and r.get("intersection_success") not in (None, ""):
        parts.append("success " + "/".join(f"{100 * float(r[f'{s}_success']):.0f}" for s in SCENARIOS) + " %")
    return ", ".join(parts)


def _write_csv(path: Path, fields: list[str], rows: list[dict]) -> None:
    with path.open("w", newline="") as f:
        w = csv.DictWriter(f, fields, extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)


def _plot_eval(rows: list[dict], path: Path, title: str, intersection: bool) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    x = [int(r["timesteps"]) / 1e6 for r in rows]
    fig, ax = plt.subplots(1, 2 if intersection else 1, figsize=(11 if intersection else 6, 4), squeeze=False)
    ax[0, 0].plot(x, [float(r["env_return"]) for r in rows], "o-")
    ax[0, 0].set(xlabel="samples (M)", ylabel="held-out episode return", title=f"{title}: training env")
    if intersection:
        for sc in SCENARIOS:
            ax[0, 1].plot(x, [100 * float(r[f"{sc}_success"]) for r in rows], "o-", label=sc)
        ax[0, 1].set(xlabel="samples (M)", ylabel="success (%)", ylim=(-5, 105),
                     title=f"{title}: PyBullet intersection ({rows[-1].get('trials')} trials)")
        ax[0, 1].legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


# ----------------------------------------------------------------------------------- shipping
def ship(args, cfg) -> int:
    from stable_baselines3 import PPO

    from racecav.common.policy import MODELS_DIR, export_policy
    from racecav.common.bench import git_commit

    run_dir = args.run_dir
    tc, record = load_run_config(run_dir)
    evals = {}
    if (run_dir / "eval.csv").is_file():
        with (run_dir / "eval.csv").open() as f:
            evals = {int(r["timesteps"]): r for r in csv.DictReader(f)}
    if args.checkpoint == "best":
        best = json.loads((run_dir / "best.json").read_text())
        ck = run_dir / "checkpoints" / best["checkpoint"]
    elif args.checkpoint == "latest":
        ck = _checkpoints(run_dir)[-1]
    else:
        ck = run_dir / "checkpoints" / f"step_{int(float(args.checkpoint)):09d}.zip"
    if not ck.is_file():
        log.error("ship: no checkpoint %s", ck)
        return 2
    model = PPO.load(ck, device="cpu")
    norm = None
    vn = ck.with_suffix(".vecnorm.pkl")
    if vn.is_file():
        import pickle

        with vn.open("rb") as f:
            norm = pickle.load(f)
    n = _step(ck)
    latest = json.loads((run_dir / "latest.json").read_text()) if (run_dir / "latest.json").is_file() else {}
    meta = {"name": args.name, "training_steps": n, "run": run_dir.name, "checkpoint": ck.name,
            "seed": tc.seed, "settings": tc.model_dump(mode="json"), "git_commit_training": record.get("git_commit"),
            "git_commit_export": git_commit(),
            "run_total_steps": latest.get("timesteps"), "run_wall_s": latest.get("wall_s"),
            "selection": evals.get(n), "obs_stack": tc.env.obs_stack, "obs_stride": tc.env.obs_stride,
            "lidar": tc.env.lidar,
            "observation": (f"sanitised lidar ranges (common/lidar.sanitize), the {tc.env.lidar!r} view "
                            f"(common/lidar.VIEWS, {VIEWS[tc.env.lidar].n_rays} rays), m"
                            + (f"; {tc.env.obs_stack} scans {tc.env.obs_stride} scan period(s) apart, newest first"
                               if tc.env.obs_stack > 1 else "")),
            "action": "[a_T, a_delta] in [-1, 1]: Gaussian mean (deterministic)"
                      + (f"; a_T < {tc.env.brake_below} brakes" if tc.env.brake_below is not None else ""),
            "brake_below": tc.env.brake_below}
    dst = MODELS_DIR / f"{args.name}.npz"
    export_policy(model, dst, meta, obs_rms=norm.obs_rms if norm else None,
                  clip_obs=norm.clip_obs if norm else 10.0, epsilon=norm.epsilon if norm else 1e-8)
    shutil.copyfile(ck, dst.with_suffix(".zip"))
    if vn.is_file():
        shutil.copyfile(vn, MODELS_DIR / f"{args.name}.vecnorm.pkl")
    save_run_record(run_dir)
    print(f"shipped {ck} as {dst} (+ .json, .zip)")
    return 0


def save_run_record(run_dir: Path) -> Path:
    """Copy what the report and a resume need into training/checkpoints/<run>/ (committed)."""
    dst = COMMITTED / run_dir.name
    dst.mkdir(parents=True, exist_ok=True)
    for name in ("config.json", "progress.csv", "eval.csv", "eval.png", "best.json", "curriculum.csv", "imitation.csv",
                 "latest.json", "latest.zip", "latest.vecnorm.pkl", "averaged.json"):
        if (run_dir / name).is_file():
            shutil.copyfile(run_dir / name, dst / name)
    return dst


# ----------------------------------------------------------------------------------- report
def report(args, cfg) -> int:
    import torch

    from racecav.common.policy import MODELS_DIR, load_policy

    torch.set_num_threads(1)
    reused = []  # the policies whose stored evaluation is reused (the page names them)
    names = [n for n in args.policies.split(",") if (MODELS_DIR / f"{n}.npz").is_file()]
    results = {}
    t0 = time.time()
    for name in names:
        pol = load_policy(name)
        meta_path = MODELS_DIR / f"{name}.json"
        meta = json.loads(meta_path.read_text())
        stored = meta.get("evaluation", {})
        if (args.reuse and stored.get("trials") == args.trials
                and (REPO / "docs" / "img" / f"training_paths_{name}.png").is_file()):
            results[name] = stored
            reused.append(name)
            continue
        res = {"trials": args.trials, "seed0": REPORT_SEED, "backend": "pybullet"}
        paths = {}
        for sc in SCENARIOS:
            r = eval_scenario(pol, sc, args.trials, REPORT_SEED, record=10)
            paths[sc] = r.pop("paths")
            res[sc] = r
            log.info("%s %s: %s", name, sc, r)
        _plot_paths(name, paths)
        res["measured"] = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
        results[name] = res
        meta["evaluation"] = res
        meta_path.write_text(json.dumps(meta, indent=2, sort_keys=True, default=str) + "\n")
    curves = _plot_curves()
    doc = REPO / "docs" / "training.md"
    doc.write_text(_markdown(results, curves, time.time() - t0, reused) + _ablation_markdown() + targets.section(
        COMMITTED, json.loads((MODELS_DIR / "avoid.json").read_text())))
    print(f"wrote {doc}")
    return 0


def draw_paths(args, cfg) -> int:
    """``racecav train paths``: a policy's ego and obstacle paths through intersection scenarios."""
    import torch

    torch.set_num_threads(1)
    try:
        policy = named_policy(args.policy)
    except (FileNotFoundError, ValueError) as e:
        print(f"racecav train paths: {e}")
        return 2
    paths, rates = {}, []
    for sc in [s.strip() for s in args.scenarios.split(",") if s.strip()]:
        try:
            r = eval_scenario(policy, sc, args.trials, SELECT_SEED, record=args.trials)
        except (FileNotFoundError, ValueError) as e:
            print(f"racecav train paths: {e}")
            return 2
        paths[f"{sc} ({100 * r['success']:.0f} %)"] = r["paths"]
        rates.append(f"{sc} {100 * r['success']:.0f} %")
    spec = Path(args.policy)  # a checkpoint's title names its run: <run>/<step>
    run = run_dir_of(spec)
    out = _plot_paths(f"{run.name}/{spec.stem}" if spec.suffix == ".zip" else spec.stem, paths, args.out)
    print(f"wrote {out}: {', '.join(rates)} of {args.trials} trials (selection seeds)")
    return 0


def _plot_paths(name: str, paths: dict, out: Path | None = None) -> Path:
    """Ego (coloured by outcome) and obstacle paths of the first trials of each scenario
    (default figure: docs/img/training_paths_<name>.png)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from racecav.common.world import load_world

    walls = load_world("intersection").walls
    fig, axes = plt.subplots(1, len(paths), figsize=(5 * len(paths), 5))
    for ax, (sc, trials) in zip(np.atleast_1d(axes), paths.items()):
        for x0, y0, x1, y1 in walls:
            ax.plot([x0, x1], [y0, y1], color="0.4", lw=1)
        for tr in trials:
            xy = np.asarray(tr["xy"])
            if not len(xy):
                continue
            c = "tab:green" if tr["success"] else ("tab:red" if tr["contact"] else "tab:orange")
            ax.plot(xy[:, 0], xy[:, 1], color=c, lw=1.2)
            ax.plot(xy[-1, 0], xy[-1, 1], "o", color=c, ms=3)
            for j in range(2, xy.shape[1], 2):
                ax.plot(xy[:, j], xy[:, j + 1], color="tab:blue", lw=0.6, alpha=0.5)
        ax.set(title=Path(sc).stem, xlim=(-8.5, 8.5), ylim=(-8.5, 8.5), aspect="equal")  # a file's stem, not its path
    n = max(len(t) for t in paths.values())
    fig.suptitle(f"{name}: ego paths, first {n} trials: green success, red contact, orange no contact but "
                 "short of min progress; blue obstacle", fontsize=9)
    fig.tight_layout()
    out = Path(out) if out is not None else REPO / "docs" / "img" / f"training_paths_{name}.png"
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=90)
    plt.close(fig)
    return out


def _runs() -> dict[str, dict]:
    out = {}
    for d in sorted(COMMITTED.glob("*")):
        if not (d / "progress.csv").is_file():
            continue
        with (d / "progress.csv").open() as f:
            rows = list(csv.DictReader(f))
        tc = load_run_config(d)[0] if (d / "config.json").is_file() else None
        out[d.name] = {"rows": rows, "config": tc, "dir": d}
    return out


def _plot_curves() -> dict[str, dict]:
    import matplotlib
    import numpy as np

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    runs = _runs()
    stats = {}
    if not runs:
        return stats
    fig, ax = plt.subplots(1, 2, figsize=(13, 7))
    colors = plt.get_cmap("tab20").colors
    for k, (name, r) in enumerate(runs.items()):
        rows = [x for x in r["rows"] if x.get("ep_rew_mean") not in ("", None)]
        x = [int(float(x["timesteps"])) / 1e6 for x in rows]
        # 20 colours x 2 line styles: 30-odd runs stay distinguishable
        style = {"color": colors[k % len(colors)], "linestyle": "-" if k < len(colors) else "--", "lw": 1}
        ax[0].plot(x, [float(x_["ep_rew_mean"]) for x_ in rows], label=name, **style)
        ax[1].plot(x, [float(x_["ep_len_mean"]) * 0.1 for x_ in rows], label=name, **style)
        sps = [float(x_["samples_per_s"]) for x_ in r["rows"][1:] if x_.get("samples_per_s")]
        last = r["rows"][-1] if r["rows"] else {}
        stats[name] = {"samples": int(float(last.get("timesteps", 0))), "wall_s": float(last.get("wall_s") or 0),
                       "samples_per_s_median": float(np.median(sps)) if sps else float("nan"),
                       "config": r["config"]}
    ax[0].set(xlabel="samples (M)", ylabel="mean episode return (last 100)", title="learning curves")
    ax[1].set(xlabel="samples (M)", ylabel="mean episode length (s)", title="episode length (time limit 60 s)")
    for a in ax:
        a.grid(alpha=0.3)
    # one legend for both panels, below them: inside a panel it covers the curves
    fig.legend(*ax[0].get_legend_handles_labels(), loc="lower center", ncol=5, fontsize=8)
    fig.tight_layout(rect=(0, 0.2, 1, 1))
    img = REPO / "docs" / "img" / "training_curves.png"
    img.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(img, dpi=100)
    plt.close(fig)
    return stats


def _markdown(results: dict, curves: dict, eval_s: float, reused: list[str]) -> str:
    L = ["# Training the racing, default, reversed-heading and avoid policies",
         "",
         "Generated by `racecav train report` (do not edit by hand; the text around the numbers",
         "lives in training/select.py and docs/training_notes.md).",
         ""]
    notes = REPO / "docs" / "training_notes.md"
    if notes.is_file():
        L += [notes.read_text().strip(), ""]
    for bj in sorted(COMMITTED.glob("bench_train_*.json")):
        rows = json.loads(bj.read_text())
        L += [f"### PPO throughput on this machine (`racecav bench train`, {bj.stem.split('_')[-1]} stage, "
              "one training process, shared 2-core box)", "",
              "| configuration | samples/s | time in PPO update | gradient steps per 1k samples |",
              "|---|---|---|---|"]
        L += [f"| {k} | {v['samples_per_s']:.0f} | {100 * v['update_share']:.0f} % | "
              f"{v['grad_steps_per_1k_samples']:.1f} |" for k, v in rows.items()]
        L.append("")
    L += ["## Runs", "",
          "| run | preset | samples | wall time | median samples/s | n_envs x n_steps | batch | epochs | normalise |",
          "|---|---|---|---|---|---|---|---|---|"]
    for name, s in curves.items():
        c = s["config"]
        if c is None:
            continue
        L.append(f"| {name} | {c.preset} | {s['samples'] / 1e6:.1f} M | {s['wall_s'] / 60:.0f} min | "
                 f"{s['samples_per_s_median']:.0f} | {c.env.n_envs} x {c.n_steps} | {c.batch_size} | "
                 f"{c.n_epochs} | {c.normalize} |")
    L += ["", "![learning curves](img/training_curves.png)", ""]
    for name in curves:
        if (COMMITTED / name / "eval.png").is_file():
            img = REPO / "docs" / "img" / f"training_eval_{name}.png"
            shutil.copyfile(COMMITTED / name / "eval.png", img)
            L += [f"Checkpoint evaluation of `{name}` (`racecav train select`):", "",
                  f"![{name} checkpoints](img/{img.name})", ""]
    L += ["## Success rates on the intersection scenarios (PyBullet, in-process)", "",
          "Success = no contact and ego progress >= the scenario's `min_progress_m`; randomised trials",
          f"(seeds {REPORT_SEED}..{REPORT_SEED}+N-1, different from the selection seeds). Paper (hardware, 10",
          "trials): DRL reversed 80/60/70 %, DRL default 80/30/70 %, MPC-APF 70/10/60 %.", "",
          "The last two columns split the failures: contact, and no contact but short of the",
          "minimum progress (the ego turned into the crossing road or stopped; see the path plots).", "",
          "| policy | shipped checkpoint | trials | " + " | ".join(SCENARIOS) + " | contact | no contact, short |",
          "|---|---|---|" + "---|" * len(SCENARIOS) + "---|---|"]
    for name, res in results.items():
        meta = json.loads((REPO / "common/data/policies" / f"{name}.json").read_text())
        succ = " | ".join(f"{100 * res[s]['success']:.0f} %" for s in SCENARIOS)
        cont = "/".join(f"{100 * res[s]['contact']:.0f}" for s in SCENARIOS)
        short = "/".join(f"{100 * (1 - res[s]['success'] - res[s]['contact']):.0f}" for s in SCENARIOS)
        L.append(f"| {name} | {meta.get('run')} {meta.get('training_steps', 0) / 1e6:.2f} M | {res['trials']} | "
                 f"{succ} | {cont} % | {short} % |")
    L += ["", f"Evaluation wall time of this report: {eval_s / 60:.1f} min"
          + (f" ({', '.join(reused)}: results reused from the policies' metadata, measured at the time "
             "shown there)." if reused else "."), ""]
    for name in results:
        if (REPO / "docs" / "img" / f"training_paths_{name}.png").is_file():
            L += [f"![{name} paths](img/training_paths_{name}.png)", ""]
    if "default" in results and "reversed" in results:
        d, r = results["default"]["head-to-head"]["success"], results["reversed"]["head-to-head"]["success"]
        L.append(f"Head-to-head: reversed {100 * r:.0f} % vs default {100 * d:.0f} % "
                 f"({'reversed better, as in the paper' if r > d else 'NOT the paper finding: reversed is not better'}).")
        rev = [100 * results["reversed"][s]["success"] for s in SCENARIOS]
        met = all(a >= b for a, b in zip(rev, PAPER_HW["reversed"]))
        L.append(f"Target (reversed >= 80/60/70 %): {'met' if met else 'not met'} "
                 f"({'/'.join(f'{v:.0f}' for v in rev)} %).")
        L.append("")
    return "\n".join(L) + "\n"


def record_observations(path: Path, seed: int = 7, scan: str = "paper") -> Path:
    """Record real observations for the SB3-vs-numpy equality test (tests/data/policy_obs.npz):
    fast-world scans with traffic (both headings, racing policy driving) and PyBullet
    intersection scans, including near-contact ones.

    ``scan="wide"``: common/lidar.WIDE_SCAN, which holds every view (tests/data/policy_obs_wide.npz,
    for policies trained on a wider view): PyBullet only (the racetrack with traffic, the paper's
    and the conflict-timed scenarios), the racing policy driving on the paper's rays of it.
    """
    import numpy as np

    from racecav.common.lidar import WIDE_SCAN, view_index
    from racecav.common.policy import load_policy
    from racecav.sim.bullet_world import BulletWorld
    from racecav.training.vec_env import FastVecEnv

    pol = load_policy("racing")
    rng = np.random.default_rng(seed)
    out = []
    if scan == "paper":
        for heading in ("default", "reversed"):
            env = FastVecEnv(n_envs=16, heading=heading, n_obstacles=15, driver="policy:racing", seed=seed)
            obs = env.reset()
            for k in range(60):
                a = pol(obs)
                a[:, 1] += rng.normal(0, 0.3, len(a))  # some off-policy wandering: walls up close
                obs, *_ = env.step(np.clip(a, -1, 1))
                if k % 20 == 19:
                    out.append(obs.copy())
    lidar = None if scan == "paper" else WIDE_SCAN
    paper = slice(None) if lidar is None else view_index(WIDE_SCAN, pol.lidar)
    scenarios = SCENARIOS if scan == "paper" else ("racetrack", *SCENARIOS, *CONFLICT_SCENARIOS)
    for sc in scenarios:
        bw = BulletWorld(sc, lidar=lidar, seed=seed)
        obs = bw.reset(seed=seed)
        for k in range(40 if sc != "racetrack" else 120):
            a = pol(obs[0][paper])
            if lidar is not None:
                a[1] = np.clip(a[1] + rng.normal(0, 0.3), -1, 1)
            obs, _, col, _ = bw.step(a)
            if k % 5 == 0:
                out.append(obs.copy())
            if col[0]:
                break
        bw.close()
    arr = np.concatenate(out).astype(np.float32)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, obs=arr)
    return path


ABLATION = (("avoid-paper", None), ("avoid-progress", "avoid-paper"), ("avoid-progress-stack2", "avoid-progress"),
            ("avoid-traffic", "avoid-progress-stack2"), ("avoid-brake", "avoid-traffic"),
            ("avoid-curriculum", "avoid-traffic"), ("avoid-wide", "avoid-curriculum"), ("avoid-lowlr", "avoid-wide"),
            ("avoid-stack3", "avoid-wide"), ("avoid-papertimed", "avoid-wide"), ("avoid-stride", "avoid-papertimed"),
            ("avoid-wide-stride", "avoid-wide"), ("avoid-dagger", "avoid-wide"),
            ("avoid-dagger-ppo", "avoid-wide"), ("avoid-bc", "avoid-wide"), ("avoid-papertimed-lowlr", "avoid-papertimed"),
            ("avoid-stride2", "avoid-papertimed"), ("avoid-papertimed-brake", "avoid-papertimed"),
            ("avoid-lane", "avoid-papertimed"), ("avoid-bc-commit", "avoid-bc"),
            ("avoid-boost", "avoid-papertimed-lowlr"), ("avoid-mirror", "avoid-papertimed-lowlr"),
            ("avoid-sym", "avoid-papertimed-lowlr"), ("avoid-augment", "avoid-papertimed-lowlr"),
            ("avoid-flow", "avoid-papertimed-lowlr"), ("avoid-flow60", "avoid-papertimed-lowlr"),
            ("avoid-flow60-std", "avoid-flow60"), ("avoid-bound", "avoid-flow60"), ("avoid-gsde", "avoid-flow60"),
            ("avoid-gsde32", "avoid-gsde"), ("avoid-gsde-flow120", "avoid-gsde32"),
            ("avoid-gsde-lowlr", "avoid-gsde-flow120"), ("avoid-gsde-flow240", "avoid-gsde-flow120"),
            ("avoid-gsde-mirrorbc", "avoid-gsde-flow120"), ("avoid-gsde-mirrorbc-anchor", "avoid-gsde-mirrorbc"),
            ("avoid-gsde-mirrorbc-sides", "avoid-gsde-mirrorbc"), ("avoid-gsde-mirrorbc-weak", "avoid-gsde-mirrorbc"),
            ("avoid-gsde-mirrorbc-wide", "avoid-gsde-mirrorbc"), ("avoid-gsde-mirrorbc-seen", "avoid-gsde-mirrorbc"),
            ("avoid-gsde-mirrorbc-seen-sides", "avoid-gsde-mirrorbc-seen"),
            ("avoid-gsde-mirrorbc-gentle", "avoid-gsde-mirrorbc-seen-sides"), ("avoid-gsde-wide", "avoid-gsde-flow120"),
            ("avoid-gsde-hold", "avoid-gsde-flow120"), ("avoid-gsde-trackbc", "avoid-gsde-flow120"),
            ("avoid-gsde-clear", "avoid-gsde-flow120"), ("avoid-gsde-clear100", "avoid-gsde-clear"),
            ("avoid-gsde-privileged", "avoid-gsde-flow120"), ("avoid-gsde-privileged-clear100", "avoid-gsde-privileged"),
            ("avoid-gsde-seenbc", "avoid-gsde-flow120"), ("avoid-gsde-holdtrack", "avoid-gsde-flow120"),
            ("avoid-gsde-holdtrack-priv", "avoid-gsde-holdtrack"), ("avoid-gsde-holdbc", "avoid-gsde-flow120"),
            ("avoid-holddagger", "avoid-gsde-flow120"), ("avoid-holddagger-ppo", "avoid-gsde-holdtrack"),
            ("avoid-gsde-open", "avoid-gsde-flow120"), ("avoid-gsde-open-hold", "avoid-gsde-open"),
            ("avoid-gsde-open-hold-brake", "avoid-gsde-open-hold"), ("avoid-gsde-brake", "avoid-gsde-flow120"),
            ("avoid-gsde-from-dagger", "avoid-gsde-flow120"), ("avoid-gsde-seen", "avoid-gsde-flow120"),
            ("avoid-gsde-heldseen-nobc", "avoid-gsde-flow120"), ("avoid-gsde-heldseen-free", "avoid-gsde-heldseen-nobc"),
            ("avoid-gsde-heldseen-track", "avoid-gsde-heldseen-free"),
            ("avoid-gsde-heldseen-track-lr", "avoid-gsde-heldseen-track"),
            ("avoid-gsde-heldseen-noflow", "avoid-gsde-heldseen-track"),
            ("avoid-gsde-heldseen-anchor", "avoid-gsde-heldseen-nobc"), ("avoid-gsde-seenanchor", "avoid-gsde-heldseen-nobc"),
            ("avoid-dagger-ppo-brake", "avoid-dagger-ppo"), ("avoid-dagger-ppo-brake-flow", "avoid-dagger-ppo-brake"),
            ("avoid-gsde-heldthrough", "avoid-gsde-heldseen-anchor"),
            ("avoid-gsde-heldthrough-wide", "avoid-gsde-heldthrough"), ("avoid-gsde-heldthrough-aux", "avoid-gsde-heldthrough"),
            ("avoid-gsde-swa", "avoid-gsde-flow120"), ("avoid-gsde-swa-avg8", "avoid-gsde-swa"),
            ("avoid-gsde-bigbatch", "avoid-gsde-flow120"), ("avoid-gsde-seenanchor-strong", "avoid-gsde-heldthrough"),
            ("avoid-gsde-seenanchor-open", "avoid-gsde-seenanchor-strong"),
            ("avoid-gsde-stoplook", "avoid-gsde-flow120"), ("avoid-gsde-stoplook-strong", "avoid-gsde-stoplook"),
            ("avoid-gsde-yield", "avoid-gsde-flow120"), ("avoid-gsde-yield-anchor", "avoid-gsde-yield"),
            ("avoid-gsde-yield-weak", "avoid-gsde-yield"), ("avoid-gsde-yield-keep", "avoid-gsde-yield"),
            ("avoid-gsde-yield-balance", "avoid-gsde-yield-keep"),
            ("avoid-gsde-yield-release", "avoid-gsde-yield-balance"),
            ("avoid-gsde-yield-follow", "avoid-gsde-yield-release"), ("avoid-gsde-yield-stride", "avoid-gsde-yield-follow"),
            ("avoid-gsde-yield-dodge", "avoid-gsde-yield-stride"),
            ("avoid-gsde-yield-dodge-balance", "avoid-gsde-yield-dodge"),
            ("avoid-gsde-yield-keepright", "avoid-gsde-yield-dodge-balance"),
            ("avoid-yield-dagger64", "avoid-gsde-yield-keepright"), ("avoid-yield-crossing128", "avoid-yield-dagger64"),
            ("avoid-yield-crossing64", "avoid-yield-dagger64"), ("avoid-yield-turn64", "avoid-yield-crossing64"),
            ("avoid-yield-nobalance64", "avoid-yield-turn64"))
"""The avoidance runs in ablation order, each with the run it adds one change to (a rejected
row's successor builds on the last kept one)."""


def _ablation_markdown() -> str:
    """The avoid policy's ablation: one row per run (committed records), its best checkpoint by
    the selection score, on the selection split (the suite's train split with selection seeds,
    fast world; the conflict-timed and paper scenarios in PyBullet with selection seeds)."""
    rows = []
    configs = {}
    for run, base in ABLATION:
        d = COMMITTED / run
        if not (d / "eval.csv").is_file():
            continue
        tc, _ = load_run_config(d)
        configs[run] = tc
        prev = configs.get(base)
        with (d / "eval.csv").open() as f:
            evals = [r for r in csv.DictReader(f) if r.get("score") not in (None, "")]
        if not evals:
            continue
        best = pick_best(evals, True)
        best["_last_score"] = max(evals, key=lambda r: int(r["timesteps"]))["score"]
        # a dagger run has no reward and no entropy bonus: their settings are not a change
        ppo_only = {"progress_reward", "contact_penalty", "ent_coef"} if "dagger" in (tc.stage, getattr(prev, "stage", "")) else set()
        change = "the paper's observation, action and reward; conflict mix" if prev is None else ", ".join(
            [f"{k} {getattr(prev.env, k)} -> {getattr(tc.env, k)}" for k in (
                "progress_reward", "obs_stack", "obs_stride", "contact_penalty", "scenarios", "scenario_share", "brake_below",
                "curriculum", "curriculum_boost", "lidar", "lane_keeping", "lane_keeping_horizon_s", "flow_reward",
                "hold_heading", "hold_track", "proximity_penalty") if getattr(prev.env, k) != getattr(tc.env, k) and k not in ppo_only]
            + [f"{k} {_shown(getattr(prev, k))} -> {_shown(getattr(tc, k))}" for k in ("stage", "learning_rate", "n_steps", "batch_size", "ent_coef", "expert_share", "bc_coef",
                                                                          "bc_label_steps", "bc_grad_steps", "bc_learning_rate", "expert_commit_s", "expert_seen",
                                                                          "expert", "mirror_families", "mirror_seen", "anchor_families", "mirror_symmetric",
                                                                          "mirror_augment", "steer_bound_coef", "sde_sample_freq", "hidden",
                                                                          "privileged_critic", "hold_until_seen", "hold_families", "hold_through", "anchor_seen", "aux_seen",
                                                                          "anchor_from", "bc_balance")
               if getattr(prev, k) != getattr(tc, k) and k not in ppo_only]
            # a reset of the loaded policy's action std (None: kept as trained, not a change)
            + ([f"init_std {prev.init_std} -> {tc.init_std}"] if tc.init_std not in (None, prev.init_std) else [])) or "-"
        if (d / "averaged.json").is_file():  # racecav train average: the base's checkpoints, averaged
            change = f"its checkpoints averaged over windows of {json.loads((d / 'averaged.json').read_text())['window']}"
        if prev is not None:
            change = f"on {base}: {change}"
            if tc.init_from != prev.init_from:
                change += f"; starts from {Path(tc.init_from).name if tc.init_from else 'scratch'}"
        rows.append((run, change, best, tc))
    if not rows:
        return ""
    fams = sorted(k.removeprefix("suite_") for k in rows[0][2] if k.startswith("suite_") and
                  k not in ("suite_success", "suite_episodes"))
    pct = lambda v: f"{100 * float(v):.0f}"  # noqa: E731
    L = ["", "## The avoid policy: training on conflicts, one change per row", "",
         "In short: the shipped avoid is row 95 at 2 M, the yield teacher (brake while a car in the scan is busy "
         "at the crossing, follow a car ahead, steer round an oncoming or stopped one) fitted by DAgger. Through "
         "the services on the test seeds it meets the issue's 8 targets as docs/results.md prints them "
         "(conflict-timed 95 / 96 / 98 %, paper-timed 100 / 98 / 100 %, suite 89 %, lowest family 76 %; the "
         "paper-timed left-to-right is 199 of 200). Before it, row 31 at 5 M (shipped 2026-12-02 to 12-05) met 7: "
         "the paper-timed left-to-right at 84 % [78, 88]. The rows below locate the cause: before the crossing car "
         "is in its scan (about 2-3 m out, behind the intersection's corners) row 31 starts a left turn that wins "
         "the conflict-timed crossing from the left and loses some paper-timed ones, which a straight ego passes. "
         "Tried against that trade-off, all rejected until rows 91-95:", "",
         "- longer training, lower learning rates, a third scan or a longer scan baseline (rows 8-9, 11-12, 16-17, 32);",
         "- the paper-timed cars in the mix with curriculum boosts, a brake, lane keeping (rows 10, 18-19, 21); "
         "a brake as the later answer on a straight approach (rows 57-58);",
         "- a privileged planner, by DAgger or as an auxiliary loss (rows 13-15, 20, 49); row 31's recipe "
         "started from row 14's policy, which drives straight through the paper-timed crossings (row 59);",
         "- mirror symmetry: the mirror image as teacher, a symmetric actor, mirrored rollouts (rows 22-24, 34-41);",
         "- reward terms: a heading hold, a ghost's straight pass, a margin to the other car (rows 43, 45-46, 50-51); "
         "the crossing car's flow and gSDE exploration were kept (rows 25-26, 29-31);",
         "- a privileged critic, a wider network (rows 38, 42, 47-48, 51);",
         "- straight-pass labels, with the car in view or before it (rows 44, 52-54);",
         "- a training mix without the conflicts that no evasion begun at first sight passes (row 60);",
         "- the straight approach forced in training until a car is in view (rows 61-65): the answers to a car in view "
         "are learnt from it, the approach the policy drives itself is not; with straight labels on the forced "
         "approach and the policy's own answers as labels after the car is in view, a wider network, an auxiliary "
         "loss for the car in view (rows 66-67, 70-72): the labels are not met where cars come into view, and the "
         "policy still turns where it drives;",
         "- the straight policy of row 14 with a brake, and with the flow term (rows 68-69): it keeps the "
         "paper-timed crossings and the free intersection, not the suite or the head-on;",
         "- the straight labels on the policy's own approach at ten times the weight, and with free "
         "intersections labelled straight (rows 76-77): the turn moves closer to the crossing, or goes and takes "
         "the suite's wins with it;",
         "- stop and look, a manoeuvre without the turn (rows 78-79; its teacher passes both timings of the paper's "
         "crossings from either side, `racecav train stop-probe`): the policies stop and win the conflict-timed "
         "crossings and 80-90 % of the suite's from the left, but pull away too slowly for the paper's 8 s files "
         "and stop before every intersection, which costs the braking, turning and head-on families;",
         "- yield, the same brake only while a car in the scan is in or closing on the crossing (rows 80-85): "
         "row 80 at 6 M passes both timings of both side crossings (conflict-timed 100 / 100 %, paper-timed "
         "97 / 96 %) but brakes for every car it sees, which loses the head-on, stopped and braking families; "
         "with those families anchored to row 31's evasions (rows 81, 83) they come back and the conflict-timed "
         "crossings are lost; balanced imitation minibatches (row 84) recover part of both (0.80 at 24.3 M); "
         "the braking family yield's until its car stops (row 85) lifts the crossings and braking (score up to "
         "0.835); turning (34-43 %) and the head-to-head stay short: the open lead;",
         "- a replicate of row 31's continuation, a larger batch, checkpoint averaging (rows 73-75): the "
         "paper-timed left-to-right of row 31's recipe is about 76 % on the selection seeds, checkpoint to "
         "checkpoint within little more than the trials' noise;",
         "- free intersections in the mix, with and without a charge for leaving the road (rows 55-56). Row 31 "
         "turns up the crossing road at an intersection with no car as well (1 % of the open suite through the "
         "services, where a straight car passes 100 %: docs/world.md and the figure below the rows' notes): the turn "
         "is a habit of the intersection, not an answer to a car, and unlearning it costs conflict-timed wins;",
         "- yield widened to every family (follow, steer round) and fitted inside PPO (rows 86-90): each family fits "
         "at the cost of another, and the conflict-timed head-to-head stays at 13-52 %;",
         "- kept: the same teacher fitted without PPO (rows 91-95), once its labels round a car agree along the "
         "policy's own path, head-on cars are met at the intersection in training too (suite head-on-crossing) "
         "and the minibatches are uniform.", "",
         "Each row is a run of `racecav train overtake --heading reversed --world figure8 --n-obstacles 8 "
         "--driver centerline --preset fast --ent-coef 0.005 --scenarios conflicts --scenario-share 0.6 "
         "--init-from common/data/policies/reversed.zip --init-std 0.4` plus the changes of the rows above and "
         "its own (the change column, relative to the run it builds on; rows 4-5 start from row 3's shipped "
         "checkpoint and row 6 from row 4's, row 7 from row 6's, with `--init-std 0.3`: the avoid policy "
         "shipped then; rows 8-13 and 15-20 from row 7's best checkpoint (52 M, shipped as avoid until the targets' pick below replaced it: `common/data/policies/avoid.zip` in their commands and config.json files is that checkpoint, committed as training/checkpoints/avoid-wide/checkpoints/step_052002816.zip; pass that path to rerun them), keeping its action std; row 7's first layer is mapped onto the wider view, training/train.map_inputs); its "
         "checkpoints are scored by `racecav train select --trials 100` on the selection split only: the "
         "suite's train split with selection seeds in the fast world (suite columns, "
         f"{rows[0][2].get('suite_episodes')} episodes) and, in PyBullet in-process with selection seeds "
         f"(SELECT_SEED = {SELECT_SEED} + k), the conflict-timed and paper-timed scenarios "
         f"({rows[0][2].get('trials')} trials each). The test split and the report seeds are never used "
         "here. Score = mean of suite, conflict-timed and paper-timed success; a change is kept only if "
         "it raises the score. The last two rows are the trivial references on the same cells and seeds "
         "(`racecav train references --trials 100`, training/checkpoints/references.csv): a car that "
         "never evades, straight at the throttle that holds 1 m/s and at full throttle. The paper-timed "
         "side columns are the ones speed alone wins. The free column (rows evaluated since it was added; "
         "not in the score) is the open suite's train split in the fast world with selection seeds: the "
         "intersection with no other car, which a straight car at full throttle passes (docs/world.md).", "",
         "| run | change | best checkpoint | score | score of the last checkpoint | suite | " + " | ".join(fams)
         + " | conflict R-L / H-H / L-R | paper R-L / H-H / L-R | free |",
         "|---|---|---|---:|---:|---:|" + "---:|" * len(fams) + "---|---|---:|"]
    free = lambda r: pct(r["free_success"]) if r.get("free_success") not in (None, "") else "-"  # noqa: E731
    for run, change, b, tc in rows:
        L.append(f"| {run} | {change} | {int(b['timesteps']) / 1e6:.1f} M | {pct(b['score'])} | {pct(b['_last_score'])} | "
                 f"{pct(b['suite_success'])} | " + " | ".join(pct(b.get(f"suite_{f}", 0)) for f in fams)
                 + " | " + " / ".join(pct(b[f"{s}_success"]) for s in CONFLICT_SCENARIOS) + " | "
                 + " / ".join(pct(b[f"{s}_success"]) for s in SCENARIOS) + f" | {free(b)} |")
    if REFERENCES_CSV.is_file():
        with REFERENCES_CSV.open() as f:
            for r in csv.DictReader(f):
                L.append(f"| *{r['reference']}* | reference: never evades (a_T = {float(r['a_throttle']):.2f}, "
                         f"steering 0) | - | {pct(r['score'])} | - | {pct(r['suite_success'])} | "
                         + " | ".join(pct(r.get(f"suite_{f}") or 0) for f in fams)
                         + " | " + " / ".join(pct(r[f"{s}_success"]) for s in CONFLICT_SCENARIOS) + " | "
                         + " / ".join(pct(r[f"{s}_success"]) for s in SCENARIOS) + f" | {free(r)} |")
    L += ["", "Without a progress term the paper's reward (5 T^2 per step, a contact ends the episode) "
          "pays as much for turning away from a conflict and circling in the crossing as for driving "
          "on: the first row's policy learned exactly that (\"short\" trials: no contact, too little "
          "progress), so its suite score falls as it trains (its eval.csv). The progress reward "
          "(`--progress-reward 18.5`: per metre along the ego's road, the same as 5 T^2 at full speed) "
          "removes the exploit. Judged by the best checkpoints alone the progress reward did not gain "
          "(second row below the first); it stays because the first row's training collapses into the "
          "exploit (its last checkpoint's score) and because the scan stack, which gains most, was trained "
          "on top of it. Row 4 (avoid-traffic) mixes the train split of a clock-timed traffic suite into the "
          "conflicts (`racecav suite generate --name traffic --n 40 --n-train 600 --seed 1`, "
          "common/data/suites/traffic.toml: crossing, head-on and turning cars at constant speed, starting "
          "after 0-4 s, which may or may not conflict; `--scenarios conflicts,traffic --scenario-share 0.7`), "
          "starting from row 3's shipped checkpoint: a policy trained on synchronised conflicts alone evades "
          "every car it sees, and this row gains mostly on the paper-timed scenarios, where the car passes "
          "if the ego keeps going. Row 5 (avoid-brake) adds a brake action (`--brake-below -0.5`: a_T < -0.5 "
          "brakes, the VESC's brake current on the car): it learned to stop in front of conflicts, which "
          "loses the head-on and stopped-car families (an oncoming car released from its synchronisation "
          "still arrives; a stopped car never leaves), and its score falls as it trains: rejected. (A first "
          "run of row 5 trained on a fast world whose brake stopped the car within one control period, "
          "while PyBullet's locked wheels need 0.2 s and 0.18 m from 2 m/s; its fast-world gains did not "
          "carry over to PyBullet. The fast world now brakes at 9.7 m/s^2 and skids straight like PyBullet, "
          "tests/test_world_contract.py, and row 5 is the rerun.) Row 6 (avoid-curriculum) builds on row 4 "
          "(row 5 rejected), from row 4's shipped checkpoint: `--curriculum` draws the scenario files by "
          "family, each family weighted by its failure rate over its last 200 training episodes (at least "
          "0.1; training/vec_env.FamilyCurriculum), with `--scenario-share 0.8 --lr 1.5e-4`. The families the "
          "policy failed most (staggered 30-45 %, cross-left 55-60 % in training at the start) get most of "
          "the episodes and rise to 70-80 % (the curriculum plot below); its checkpoints score 82-89, and "
          "every one up to 31 M samples (85-89) is above row 4's best. Kept and shipped. The conflict-timed "
          "left-to-right scenario swings most between checkpoints (40-84 %) while the suite holds at 79-86 %; "
          "the checkpoints after 31 M score lower (82-85), so the run stopped at 40 M. Budgets differ (5-40 M samples: the runs "
          "shared two cores with the rest of the sessions' work), and one run per row is one seed: "
          "differences under ~5 points are noise; single checkpoints of one run swing by 5-10 points "
          "(row 4: 72-82 between 16 M and 23 M samples). Row 7 (avoid-wide) builds on row 6 with the wide "
          "lidar view (`--lidar wide`: 169 rays over +-89.7 deg instead of 170 over +-45 deg, docs/world.md), "
          "from row 6's shipped checkpoint: the first layer is mapped onto the new rays (two paper rays add "
          "into the wide ray between them, the rays beyond +-45 deg start at zero; training/train.map_inputs, "
          "tests/test_lidar_views.py). Why: a car crossing from the ego's left at 45-73 deg stays at a "
          "constant bearing of about 50 deg on a collision course, outside the paper's view, and row 6 "
          "wins only ~40 % of those (fast world, cross-left train files by heading tercile). The wide view "
          "starts lower (halving the ray density changes what the old weights see) and climbs from 0.81 "
          "at 5 M to 0.88 at 38-45 M samples: it gains the suite (84-91 % on the train split against row "
          "6's 86, staggered 85-92 against 79, stopped 87-91 against 82) and the conflict-timed "
          "left-to-right scenario (85-97 % against 84), but loses the conflict-timed head-on (48-74 % "
          "against 85) and the paper-timed left-to-right (59-77 % against 85): with the crossing car in view "
          "from the start it evades cars that would have passed. Up to 45 M its best score (0.88) stays below "
          "row 6's (0.89); the run went on to 60 M (`racecav train overtake --resume --run-dir runs/avoid-wide "
          "--steps 60e6`), and its 52 M checkpoint scores 0.92 (suite 91, conflict-timed 100 / 84 / 99, "
          "paper-timed 100 / 98 / 76), the first above row 6, while its neighbours score 0.80-0.89: the "
          "row is kept by the rule, but that one checkpoint is the best of 26 evaluated and the paper-timed "
          "left-to-right stays its weak cell. Shipped as avoid until 2026-12-01 (through the services on the test "
          "seeds and split: conflict-timed 100 / 84 / 98 %, paper-timed 98 / 94 / 68 %, suite 92 %; docs/results.md at "
          "commit 92dd3ab), then replaced by the targets' pick (row 16 at 4 M, below). "
          "Row 8 (avoid-lowlr) continues from row 7's 52 M checkpoint with a third of its learning rate "
          "(5e-5) and its action std as trained, to hold that point while it improves. It moves along the "
          "same trade-off instead: from 11 M samples on the conflict-timed head-on recovers (79-94 %, "
          "against 84 at the start) and the suite's train split holds at 87-94 %, but the paper-timed "
          "left-to-right falls to 19-52 % (65 % after 3 M). Row 7's paths show the mechanism, and row 16's "
          "(the avoid paths figure while it was shipped, at commit 4bd9615) show the same: in most trials it turns left into the crossing road. Behind a car that "
          "arrives with the ego (the conflict-timed case) that road is free; the paper's left-to-right "
          "car, which a straight ego would have passed, is still in it. Its best score "
          "stays below row 7's: rejected. Row 9 (avoid-stack3) builds on row 7 with a third scan in the "
          "stack (`--obs-stack 3`; the third slot's weights start at zero, so it starts as row 7). Why: in "
          "two scans 0.1 s apart a crossing car that will pass ahead of or behind the ego moves by about "
          "one wide ray (~20 deg/s of bearing at 3-4 m), while one on a collision course keeps its "
          "bearing; a third scan doubles that baseline. It drifts as row 8 does: from 18 M samples on the "
          "conflict-timed scenarios are at 98-100 / 80-87 / 89-93 % but the paper-timed left-to-right at "
          "24-42 %, and its checkpoints score 0.79-0.89, below row 7's best. Stopped at 21 M and rejected "
          "(it can go on with `racecav train overtake --resume --run-dir runs/avoid-stack3 --steps 60e6`). "
          "Rows 8 and 9 suggest that the trade-off comes from the training mix rather than from what the "
          "policy sees: "
          "the longer it trains on it, the more it turns away from every car crossing from its left. "
          "Row 10 (avoid-papertimed) tests that: it adds a third training suite, cars timed like the "
          "paper's Table 1 (`racecav suite generate --name paper-timed --n 40 --n-train 600 --seed 2`, "
          "common/data/suites/paper-timed.toml, docs/world.md: crossing and head-on cars at a constant "
          "speed that brings them to the conflict point when an ego holding its start speed gets there, "
          "0-0.3 s late; a straight ego at full throttle passes ahead of the crossing cars), with "
          "`--scenarios conflicts,traffic,paper-timed`, from row 7's shipped checkpoint (avoid.zip, its "
          "52 M step) and its action std. Its first checkpoints stay near row 7 (0.89 and 0.91 at 1-2 M "
          "samples: suite 90, conflict-timed 100 / 79 / 93, paper-timed 100 / 99 / 79), then it falls to "
          "0.77-0.85 from 4 M on: the conflict-timed head-on drops to 47-56 % and the paper-timed "
          "left-to-right does not rise (42-73 %). In training the two cross-left families trade against "
          "each other (curriculum.csv: the paper-timed one 0.57-0.81, the conflict one 0.59-0.83, "
          "neither rising). Stopped at 14 M, rejected. Row 11 (avoid-stride) adds to row 10 a stack of "
          "two scans 0.4 s apart instead of 0.1 s (`--obs-stride 4`; the same 338 inputs, so the same "
          "act time). Why: a crossing car on a collision course keeps its bearing, while one that "
          "will pass ahead of or behind the ego drifts; early in an approach that drift between "
          "consecutive scans is small against the 1.06 deg between wide rays, and a four times longer "
          "baseline makes it four times larger. `--init-from` re-strides the first layer so that the model starts with the "
          "old response to steady motion (training/train.restride, tests/test_obs_stride.py). It starts "
          "lower (0.83 at 1 M) and drifts further: the paper-timed left-to-right rises slowly (41-72 %), "
          "but from 16 M samples on the conflict-timed left-to-right falls to 27-46 % and the head-on to "
          "39-62 %, scores 0.72-0.86. Stopped at 21 M, rejected. With the paper-timed cars in the mix the "
          "policy gives up the conflicts it had learnt instead of telling the two timings apart, with or "
          "without the longer baseline, within these budgets. Row 12 (avoid-wide-stride) adds the longer "
          "baseline alone to row 7 (`--obs-stride 4`, row 7's mix `--scenarios conflicts,traffic`), "
          "from row 7's shipped checkpoint. It keeps the conflicts better than rows 10-11 but does not "
          "reach row 7: from 3 M samples on, conflict-timed 92-100 / 63-89 / 80-95 %, the suite's train "
          "split 81-88 %, paper-timed 97-100 / 77-97 / 33-66 %; scores 0.80-0.87 up to 26 M (47 min). "
          "Stopped, rejected; resumable (`racecav train overtake --resume --run-dir runs/avoid-wide-stride "
          "--steps 60e6` after copying training/checkpoints/avoid-wide-stride to runs/, as above). Row 7 needed "
          "52 M samples for its best checkpoint (0.92), whose neighbours scored 0.80-0.89. Rows 8-12 all "
          "start from that checkpoint, and none of their 78 evaluated checkpoints scores above it (their "
          "best: 0.91, 0.89, 0.91, 0.86, 0.87). Row 13 (avoid-dagger) replaces PPO by imitation of a "
          "privileged planner, with row 7's observation and training mix, from row 7's shipped checkpoint "
          "(`racecav train dagger --preset fast --run-dir runs/avoid-dagger --steps 3e6 --checkpoint-every "
          "65536 --world figure8 --heading reversed --n-obstacles 8 --driver centerline --scenarios "
          "conflicts,traffic --scenario-share 0.8 --curriculum --obs-stack 2 --lidar wide --init-from "
          "common/data/policies/avoid.zip --expert-share 0.3`; training/dagger.py, training/expert.py). "
          "Why: rows 8-12 suggest that PPO's only signal, a contact or a success seconds after the "
          "decision, does not teach the policy which of two similar scenes needs an evasion. The planner "
          "steps exact copies of the fast world (the actors' triggers and synchronisation included) 2.5 s "
          "ahead for 14 candidates at full throttle (13 steering actions held 0.3 or 0.8 s, and plain "
          "tracking of its road) and keeps tracking unless a manoeuvre scores 0.1 m of progress better; it passes the three conflict-timed scenarios "
          "(tests/test_dagger.py). Each step of the policy's own rollouts (30 % of the episodes driven "
          "by the planner) is labelled with the planner's action, and the policy's mean action is fitted "
          "to all labels so far (DAgger). At 260-320 samples/s (the planner costs ~0.2 s per control "
          "step of 64 worlds) it ran 0.36 M samples in 21 min: the policy learns the paper-timed side "
          "scenarios (99-100 % from the first checkpoint; a straight car at full throttle scores 100 % "
          "there too (docs/results.md, test seeds): the planner does not evade a car that a fast straight ego passes) and the suite's head-on family (84-96 % from 0.2 M samples on), but not the crossings that need an "
          "evasion (suite cross-left 11-31 %, staggered 24-38 %, conflict-timed left-to-right 2-60 %); "
          "its checkpoints score 0.64-0.74 and its own episodes succeed in 37-69 % of the scenarios in "
          "training after the first checkpoint (progress.csv); its steering "
          "agrees with the planner's within 0.05 rad on 44-60 % of the steps. From the scans it sees, "
          "the 2 x 64 network does not reproduce the planner's timing-dependent choices within this "
          "budget (imitation loss still falling slowly, 0.46 at 65 k samples to 0.34). Stopped, rejected. "
          "Row 14 (avoid-dagger-ppo) is row 7's PPO run, same command and mix, started from row 13's "
          "0.2 M checkpoint instead of row 6's policy (`--init-from training/checkpoints/avoid-dagger/"
          "checkpoints/step_000196608.zip`, committed). Why: PPO from row 7's policy always drifted into "
          "turning left away from every car crossing from the left (rows 8-12); the imitation starts it "
          "from a policy that passes the paper-timed side scenarios. It holds both left-to-right timings "
          "together better than any earlier row: at its six checkpoints from 11 M samples on, paper-timed "
          "left-to-right 93-99 % and conflict-timed left-to-right 84-97 % (66 % at the last), but it has "
          "not relearnt the head-on (conflict-timed 27-92 %, paper-timed 72-81 %) or the suite (70-77 % on "
          "the train split): scores 0.72-0.84 up to 16.5 M samples (35 min). Resumed in the next session "
          "(`racecav train overtake --resume --run-dir runs/avoid-dagger-ppo --steps 80e6`, 8.8 k samples/s) "
          "to 30.8 M: its checkpoints from 23 M on score 0.83-0.85 (best 0.85 at 30.8 M: conflict-timed "
          "96 / 85 / 99 %, paper-timed 100 / 65 / 99 %) but the suite stays at 71-77 % on the train split, "
          "against row 7's 91: rejected, stopped for a run with better odds (resumable as above). "
          "Row 15 (avoid-bc) keeps PPO and adds the planner as an auxiliary loss instead: row 7's command "
          "from row 7's checkpoint with `--bc-coef 0.1` (training/imitation_term.py: the planner labels every "
          "world at 2 random steps of each rollout, and after each PPO update 20 minibatches of the imitation "
          "loss x 0.1 go through PPO's optimizer; the labels cost about a third of the throughput, 5.3-6 k "
          "samples/s). The labels pull the policy away from row 7 faster than PPO holds it: the training "
          "return falls from 770 to 520 within 0.4 M samples and its checkpoints score 0.41, 0.61 and 0.64 "
          "at 1, 2 and 3 M (paper-timed side scenarios 100 % from 2 M on, as row 13; suite 49-62 %). "
          "Its steering agrees with the newest labels within 0.05 rad on only 9-36 % of them while the "
          "loss on the aggregate falls from 12 to 0.7 (imitation.csv): in 40 % of the labels the planner "
          "picks a held steering manoeuvre over plain tracking for a gain of a few decimetres, targets the "
          "policy's view does not determine. Stopped at 3.4 M, rejected. "
          "Row 16 (avoid-papertimed-lowlr) is row 10 (the paper-timed cars in the mix) at row 8's third of the "
          "learning rate (`--lr 5e-5`), from row 7's checkpoint. Why: row 10 gained the paper-timed "
          "left-to-right in its first 2 M samples and then drifted, as row 7 did at 1.5e-4 while row 8 at 5e-5 "
          "held. 42 M samples in 82 min (a median 9.0 k samples/s): it holds the conflict-timed scenarios and the suite "
          "(conflict-timed 86-100 / 70-96 / 89-99 %, suite 89-92 % over its 22 evaluated checkpoints; at 4 M "
          "99 / 96 / 98 % and 92 %, the best conflict-timed head-on of any row), but the paper-timed "
          "left-to-right stays at 31-74 % (its training success on the paper-timed crossings from the left "
          "rose from 67 to 83 % by 24 M and fell back to 72 %, curriculum.csv): scores 0.85-0.91, the best "
          "(0.909 at 4 M and at 20 M) below row 7's 0.92. Rejected by the score, but its 4 M checkpoint "
          "(committed in training/checkpoints/avoid-papertimed-lowlr/checkpoints/) meets more of the issue's "
          "targets than any other until row 31; shipped as avoid from 2026-12-01 to 2026-12-02 "
          "(through the services on the test seeds and split: conflict-timed 99 / 96 / 94 %, paper-timed "
          "94 / 95 / 57 %, suite 92 %; docs/results.md at commit 47b5997, measured while the sim service's "
          "episodes were one control period apart in the stamps, so that the policy's first scan stack of "
          "each trial held the previous trial's last scan: docs/world.md). In 8 traced paper-timed left-to-right "
          "trials (PyBullet, a one-off script) row 7's 52 M checkpoint failed 5 times, each by turning left into the "
          "crossing road to pass behind a car that a straight ego would have passed ahead of: the two timings "
          "look alike in its view until it has turned. "
          "Row 17 (avoid-stride2) is row 11 with half its baseline: two scans 0.2 s apart (`--obs-stride 2`) "
          "on row 10, from row 7's checkpoint (re-strided as in row 11). Why: row 11's four-fold baseline "
          "changed what the old first layer sees the most; a two-fold one might keep row 7's conflicts while "
          "showing a slower bearing drift. 24.5 M samples in 48 min: scores 0.80-0.90 over 10 checkpoints "
          "(best 0.90 at 22 M: conflict-timed 100 / 88 / 96 %, paper-timed 97 / 98 / 70 %, suite 87 % on the "
          "train split), the paper-timed left-to-right at 22-70 %: below row 7, rejected. The probe below "
          "says why no stride was going to help. "
          "Row 18 (avoid-papertimed-brake) adds the brake action to row 10 (`--brake-below -0.5`), from row 7's "
          "checkpoint. Why: the probe below places the difference between the two timings within about 2 m of "
          "the crossing, and a brake is the action that still changes the ego's arrival that late; row 5 "
          "tried it only on an earlier base (no curriculum, no wide view, no paper-timed cars). 31.9 M samples "
          "in 71 min: scores 0.82-0.90 over 14 checkpoints (best 0.90 at 26 M: conflict-timed 97 / 88 / 94 %, "
          "paper-timed 98 / 98 / 72 %, suite 88 % on the train split), the paper-timed left-to-right at "
          "62-80 % and the conflict-timed head-on at 57-88 %. Its deterministic policy hardly brakes: at "
          "19 M it brakes in 0-2 % of the episodes of every family of both suites (fast world, 1024 worlds "
          "per suite, a one-off count). Below row 7, rejected. "
          "Row 19 (avoid-lane) adds a reward term to row 10 (`--lane-keeping 2 --lane-keeping-horizon 1.2`, "
          "training/lane_keeping.py), from row 7's checkpoint. Why: a later decision can still pass both "
          "timings (the privileged planner held straight until 2 m from the conflict point passes every "
          "cross-left file of both, the probe below), while the policy commits between 2.5 and 2 m. At each "
          "step of a scenario episode where tracking the ego's road at full throttle would pass free for "
          "1.2 s (the planner's look-ahead on an exact copy of the world), the term adds -2 x |a_delta - "
          "the tracking steer|, so steering before a conflict is certain costs reward. The look-ahead costs "
          "throughput: 11.4 M samples in 88 min (a median 2.3 k samples/s, against 8-9 k for row 10). "
          "It does not teach the late evasion: scores 0.84-0.89 over 11 "
          "checkpoints, falling after 5 M (0.89 at 4 M and at 5 M, the table's row: conflict-timed 97 / 91 / "
          "87 %, paper-timed 100 / 94 / 60 %, suite 90 % on the train split); the paper-timed left-to-right "
          "at 40-67 % and the "
          "conflict-timed head-on at 71-91 %. Below row 7, rejected. "
          "Row 20 (avoid-bc-commit) is row 15 with the planner's labels gated (`--expert-commit-s 1.0`, "
          "training/expert.Expert's commit_s): the planner labels a manoeuvre only where tracking its road "
          "would touch something within 1.0 s, and plain tracking everywhere else. Why: row 15's labels chose "
          "a manoeuvre in 40 % of the steps for small gains the view does not determine, while the planner "
          "gated this way still passes all 128 fast worlds per suite drawn from the cross-left train files of "
          "both timings (a one-off run, commit 0.8-1.5 s) and labels a manoeuvre in 6 % of the conflict-timed "
          "cross-left steps and in none of the paper-timed ones. Its labels are manoeuvres in 10-13 % of "
          "the steps (imitation.csv), but the policy still collapses first: the training return falls from "
          "770 to 420 within 50 k samples, and after 6.6 M samples (22 min, a median 5.5 k samples/s) the "
          "crossing families are at 19-49 % in training (staggered 19, cross-left 29, cross-right 49 %; "
          "curriculum.csv). Its 6.6 M checkpoint drives straight through the crossings, as rows 13 and 15 "
          "did: paper-timed 100 / 88 / 100 %, conflict-timed 13 / 94 / 5 %, suite 57 %, score 0.64. "
          "Stopped, rejected; resumable (`racecav train overtake --resume --run-dir runs/avoid-bc-commit "
          "--steps 60e6`). "
          "Row 21 (avoid-boost) is row 16 from its 4 M checkpoint (the avoid shipped then) with the paper-timed "
          "crossings from the left drawn three times as often as their failure rate says "
          "(`--curriculum-boost paper-timed/cross-left=3`, EnvConfig.curriculum_boost). Why: the view tells "
          "the two timings apart only late (the probe below), so a policy can only move along the trade-off "
          "between them, and row 16's curriculum weighed both cross-left families alike (each failing about "
          "a quarter of the time). 28.6 M samples in 74 min (a median 6.4 k samples/s, with the selection "
          "on the second core). It does not move the trade-off: in training the paper-timed crossings from "
          "the left stay at 66-81 % and the conflict-timed ones at 72-86 % (row 16's first 4 M: 61-77 and "
          "76-86 %; curriculum.csv), and over its 20 evaluated checkpoints the paper-timed left-to-right is "
          "at 37-78 % with no trend (37 % at 23 M, 78 % at 13 M) and the conflict-timed head-on at 72-94 %. "
          "Scores 0.88-0.92: the best, 0.916 at 13 M (conflict-timed 98 / 85 / 95 %, paper-timed 98 / 97 / "
          "78 %, suite 91 %; the table shows 20 M, in the same 0.05 step of the score with a higher suite), "
          "is below row 7's 0.92, and no checkpoint meets more of the targets than row "
          "16's 4 M (7 of 8 at best, at 1 M, with a lower score). Its 11 M checkpoint (committed in "
          "training/checkpoints/avoid-boost/checkpoints/) is the nearest miss: at 300 trials per scenario and "
          "1536 suite episodes (`racecav train select --trials 300 --suite-episodes 1536` on a run folder that "
          "holds only it) conflict-timed 99 / 93 / 97 %, paper-timed 99 / 98 / 70 %, suite 90 % (lowest family "
          "73 %), score 0.917: 6 of 8, one point of the paper-timed right-to-left short of row 16's 7, "
          "with 17 points more of the left-to-right than row 16's 53 %. Rejected. "
          "Row 22 (avoid-mirror) starts from what the mirror table below found: row 16 at 4 M "
          "(the avoid shipped then) passes both timings of the crossings from its right, and its own mirror image (scans "
          "reversed, steering negated) passes both timings from the left (paper-timed left-to-right 98 %, "
          "conflict-timed 99 %, the paper-timed suite's crossings from the left 99 %), so the skill the "
          "left side lacks is in the network, on the other side. It imitates itself "
          "(`racecav train dagger --expert mirror --mirror-families cross-left --expert-share 0.3 --lr 1e-5 "
          "--grad-steps 100`, row 16's env flags, `--init-from` row 16's 4 M checkpoint; training/mirror.py): "
          "each step of a crossing from the left, once its car is within 5 m on the ego's left, is labelled "
          "with the mirrored action, every other step with the policy's own, so only the left crossings "
          "should change. They do not change alone: the steering agrees with the labels within 0.05 rad on "
          "99 % of the steps before the first fit and on 83 % after 0.3 M samples (progress.csv; 5 % of the "
          "labels are mirrored), and at 1.0 and 1.3 M samples (1.3 M in 3.5 min) the conflict suite has "
          "fallen to 59 % (crossings from the right 64-65 %, from the left 21-23 %, braking 41-42 %) and the "
          "conflict-timed left-to-right to 1-3 %, while the paper-timed left-to-right rose to 68-77 %: scores "
          "0.65-0.67. Regression moves the mean action by a little everywhere, and the evasions of the "
          "conflict-timed cars (synchronised with the ego until 0.8 s before the crossing) do not survive a "
          "little. Stopped, rejected. "
          "Row 23 (avoid-sym) makes the actor mirror-symmetric by construction (`--mirror-symmetric`, "
          "training/symmetric.py): the same 2 x 64 tanh MLP whose hidden units come in mirrored pairs, the tie "
          "kept by projection after every PPO step and the input statistics kept symmetric, so its action on "
          "the mirrored scans is its action mirrored, exactly (tests/test_symmetric.py), and it learns each "
          "side from both sides' episodes. The export, the numpy path and the fused kernel are unchanged. "
          "Row 16's weights have no symmetric neighbour (the mean of two unrelated units is neither), so it "
          "starts from scratch, with row 16's env, mix and curriculum at the default learning rate "
          "(`racecav train overtake --preset fast --run-dir runs/avoid-sym --world figure8 --heading reversed "
          "--n-obstacles 8 --driver centerline --scenarios conflicts,traffic,paper-timed --scenario-share 0.8 "
          "--curriculum --obs-stack 2 --progress-reward 18.5 --ent-coef 0.005 --lidar wide --mirror-symmetric "
          "--checkpoint-every 1e6`). 31.6 M samples in 79 min (a median 6.7 k samples/s): the paper's two "
          "side scenarios now move together (right-to-left / left-to-right 70 / 74, 53 / 49, 65 / 68 % at "
          "1, 10 and 29 M; at most 11 points apart over its 10 evaluated checkpoints), but nothing is learnt "
          "well: scores 0.41-0.58 (best 0.58 at 10 M: paper-timed 53 / 57 / 49 %, conflict-timed 62 / 58 / "
          "58 %, suite 61 %), and in training the crossing families stay at 27-57 % from 10 M samples on "
          "(curriculum.csv; staggered 13-31 %). Row 1, from the paper's reversed policy, was at 0.69 after "
          "5 M. The symmetric actor also drives a lopsided car: the steering reaches 0.313 rad to the left and "
          "0.263 to the right (common/data/cars/slash.toml), so a mirrored evasion to the right is a weaker "
          "one; in training it passes the conflict suite's crossings from the left more often than those from "
          "the right (32-57 % and 27-47 % from 10 M on). Stopped, below every earlier row; resumable (`racecav train overtake --resume "
          "--run-dir runs/avoid-sym --steps 80e6` after copying training/checkpoints/avoid-sym to runs/). "
          "An exactly symmetric actor has a second handicap: in a scene that is its own mirror image (a car "
          "or a stopped car dead ahead) its steering is zero, so it must break the tie from the small "
          "asymmetries of the scene; its head-on cells (paper-timed 57 %, conflict-timed 58 %) are as low as "
          "its crossings. "
          "Row 24 (avoid-augment) keeps row 16's network and PPO's objective and lets every update also fit "
          "its rollout seen in a mirror (`--mirror-augment`, training/augment.py: each sample's scans "
          "reflected and its steering negated, with the same return and advantage and the policy's own "
          "log-probability as the old one, so PPO's ratio starts at 1 and its clip bounds each update; the "
          "usual symmetry augmentation for PPO), from row 16's 4 M checkpoint with its flags and learning "
          "rate. It collapses within 0.5 M samples: the reflected samples ask a lopsided policy for the "
          "opposite steering in the same scenes (PPO's approx_kl a median 13 per update and up to 3e9, "
          "against 0.006-0.015 for row 16; progress.csv), and the way from a policy that turns left for every car to one that turns each way "
          "passes through one that turns neither way: the conflict-timed scenarios fall to 0-6 % at once "
          "(the paper-timed ones hold 95 / 96 / 52 % at 0.5 M, a straight car's strategy), the suite to "
          "36 % and then 23 %; scores 0.40, 0.22 and 0.19 at 0.5, 1.0 and 1.5 M (5 min, a median 4.7 k samples/s: each update "
          "fits twice the samples). Stopped, rejected. "
          "Row 25 (avoid-flow) starts from what row 16's paths show (the avoid paths figure at commit 4bd9615): it "
          "turns left at the intersection in all three paper scenarios. For the car from the right, moving "
          "to the ego's left, that turn runs ahead of the car in its own direction of travel and passes both "
          "timings; for the car from the left it enters the road the car is coming down and passes only once "
          "the car has gone. Its mirror image (the mirror table below) turns right for the car from the left, "
          "with that car's flow, and passes both of its timings (paper-timed 98 %, conflict-timed 99 %): the "
          "evasion with the crossing car's flow is the one that does not depend on the timing, and PPO did "
          "not find it from the left-turn habit in rows 8-23. Row 25 pays for it while it is learnt "
          "(`--flow-reward 20`, training/flow_reward.py: 20 per metre the ego moves along the direction of "
          "travel of a moving car that crosses its road at 45-135 deg within 4 m, negative against it; about "
          "the progress reward's rate), with row 16's flags and learning rate, from row 16's 4 M checkpoint. "
          "6.0 M samples in 13 min: scores 0.91-0.92 at 2, 4 and 6 M, the paper-timed left-to-right at "
          "65-72 % (row 16's checkpoints up to 11 M: 45-62 %), conflict-timed 99-100 / 90-96 / 91-97 %, "
          "but its lowest suite family at 57-67 %: 6 of the 8 targets. Stopped for a stronger weight. "
          "Row 26 (avoid-flow60) is row 25 with three times the weight (`--flow-reward 60`). 12.5 M samples "
          "in 28 min: its 2 M checkpoint scores 0.925, the highest of any row but above row 7's 0.922 by far "
          "less than the noise (conflict-timed 99 / 93 / 97 %, paper-timed 96 / 98 / 79 %, suite 90 %, lowest "
          "family 70 %; the table shows 1 M, in the same 0.05 step of the score with a higher suite), and the checkpoints after it fall "
          "(0.91, 0.88, 0.87 and 0.83 at 3, 5, 7 and 12.5 M): the paper-timed left-to-right is at 56-71 % "
          "and then 85 % at 12.5 M, while the conflict-timed head-on falls to 79-84 % and then 50 % and the "
          "conflict-timed left-to-right to 73 %, the same trade-off as rows 8-21. In training the crossings from the left do not rise (the paper-timed "
          "ones 61-85 %, the conflict-timed ones 59-87 % from 2 M on, as row 16's 60-83 and 72-90 %; "
          "curriculum.csv). Kept by the rule, on one checkpoint as row 7 was; that checkpoint meets 6 of the 8 targets "
          "(missing the paper-timed right-to-left, 96 %, and left-to-right, 79 %), one fewer than row 16's "
          "4 M, which stays the targets' pick. Its 2 M checkpoint is committed "
          "(training/checkpoints/avoid-flow60/checkpoints/). "
          "Row 27 (avoid-flow60-std) continues row 26 from that checkpoint with a wider steering noise "
          "(`--init-std 0.3`: the action stds of that checkpoint, its log_std, are 0.53 for the throttle "
          "and 0.08 for the steering, which explores little, and a steering beyond the car's range, "
          "clipped by the actuation, does not explore at all). 10.3 M samples in 23 min: scores 0.88-0.91 over 7 evaluated checkpoints, the paper-timed "
          "left-to-right at 58-82 % and the conflict-timed head-on at 66-98 %, with the std back at 0.22 by "
          "10 M: the same trade-off. Stopped, rejected. "
          "Row 28 (avoid-bound) takes the saturation itself away: a loss on the steering mean beyond the "
          "car's range (`--steer-bound-coef 10`, training/bounds.py, rl_games' bounds loss on the steering "
          "alone) pulls the mean back to the edge of the range, where the car does the same and the sampled "
          "actions do vary the turn; row 26's flags, from row 16's 4 M checkpoint. 6.4 M samples in 18 min: "
          "the conflict-timed left-to-right rises to 93-98 % and the suite's crossings from the right to 97-100 % "
          "from 2 M on, while the paper-timed left-to-right falls to 0-17 % and the conflict-timed head-on to "
          "39-59 %: scores 0.64-0.77 over its 6 checkpoints, each below row 26's. Stopped, rejected. "
          "Row 29 (avoid-gsde) keeps the actuation's clip and makes the exploration last instead: SB3's "
          "generalised state-dependent exploration (`--sde-sample-freq 8`: the noise is a random linear "
          "function of the last hidden layer, drawn anew every 8 steps, 0.8 s, so an exploratory turn is "
          "held long enough to change the car's path; `--init-std 0.3` calibrates its weights so the action "
          "std averages 0.3 over the first observations, training/train.calibrate_sde; the std column of "
          "progress.csv of rows 29-57 is then SB3's noise weights' mean, not the action's; runs started or resumed "
          "since then log the action std, training/train.action_std), row 26's flags, from row 16's 4 M "
          "checkpoint. 26.8 M samples in 61 min: unlike rows 8-27 it does not drift into the trade-off "
          "within 10 M samples: scores 0.87-0.93 at every checkpoint to 10.3 M (the paper-timed left-to-right "
          "at 61-88 %, the conflict-timed head-on at 77-89 %, the suite at 90-94 %), then 0.86-0.90 from 12 to "
          "26.8 M with the paper-timed left-to-right back at 46-70 % (stopped). Its best, 0.928 at 3 M (conflict-timed 99 / 85 / "
          "92 %, paper-timed 100 / 94 / 88 %, suite 92 %, lowest family 74 %; the table shows 5 M, in the same 0.05 step of the score with a higher suite), is above row 26's 0.925 by far "
          "less than the noise; kept by the rule; it meets 6 of the 8 targets (missing the conflict-timed head-on and the "
          "paper-timed left-to-right), row 16's 4 M 7. "
          "Row 30 (avoid-gsde32) draws the noise every 32 steps (3.2 s, an approach and its evasion). "
          "9.1 M samples in 22 min: scores 0.87-0.93 (best 0.929 at 7 M: conflict-timed 100 / 91 / 98 %, "
          "paper-timed 99 / 96 / 77 %, suite 92 %, lowest family 67 %; the table shows 4 M, as above), the paper-timed left-to-right at "
          "43-85 %, the conflict-timed head-on at 81-96 %; kept by the rule (again within the noise). Its "
          "1-4 M and 8 M checkpoints meet 6 of the 8 targets and none more (row 16's 4 M: 7). gSDE slows "
          "the drift of rows 8-28 (rows 29-30 score 0.87-0.93 for 9-10 M samples), but within these budgets "
          "the paper-timed left-to-right stays at most 88 %. Its 7 M checkpoint is committed "
          "(training/checkpoints/avoid-gsde32/checkpoints/). "
          "Row 31 (avoid-gsde-flow120) is row 30 with the flow weight doubled (`--flow-reward 120`), from "
          "row 16's 4 M checkpoint. 15.3 M samples in 37 min (12 checkpoints evaluated): scores "
          "0.90-0.93, the paper-timed left-to-right at 59-88 % and the conflict-timed head-on at 77-99 %. Its "
          "5 M checkpoint scores 0.934, the highest of any row (conflict-timed 99 / 92 / 97 %, paper-timed "
          "100 / 94 / 83 %, suite 92 %, lowest family 74 %; the table shows 8 M, as above), and meets 7 of the 8 targets, as row 16's 4 M "
          "does (score 0.910), with 32 points more of the paper-timed left-to-right (83 % against 51 %); "
          "kept, committed (training/checkpoints/avoid-gsde-flow120/checkpoints/), the targets' pick until row 95. Neither meets the "
          "paper-timed left-to-right's 100 %. Shipped as avoid on 2026-12-02 (through the services on the test "
          "seeds and split: conflict-timed 100 / 92 / 98 %, paper-timed 100 / 92 / 82 %, suite 92 %, lowest "
          "family 76 %, docs/results.md of 2026-12-02 14:15 UTC, with the sim's gap between episodes): 7 of the "
          "8 targets, short of the paper-timed left-to-right. "
          "Row 32 (avoid-gsde-lowlr) continues row 31 from its 5 M checkpoint (the avoid shipped then) at 2e-5, two "
          "fifths of its learning rate, with the noise as trained (no `--init-std`), to hold that point while it "
          "improves. 14.4 M samples (80 min of wall time, 35 of them paused during CI runs, beside the results table; evaluated "
          "at 1, 4, 7 and 10 M with `--every 3`): scores 0.91-0.93, the paper-timed left-to-right at 83-90 %, the "
          "conflict-timed head-on at 82-92 %, the lowest suite family at 66-70 %; its checkpoints meet 5 or 6 of "
          "the 8 targets, none more than row 31's 7. Stopped, rejected; its 4 M checkpoint (0.934) is committed "
          "(training/checkpoints/avoid-gsde-lowlr/checkpoints/), and it resumes with `racecav train overtake "
          "--resume --run-dir runs/avoid-gsde-lowlr --steps 60e6` after copying that folder to runs/. "
          "Row 33 (avoid-gsde-flow240) doubles the flow weight again (`--flow-reward 240`), from row 16's 4 M "
          "checkpoint with `--init-std 0.3`, as row 31. 7.9 M samples in 21 min (evaluated to 5 M, then stopped for "
          "row 34): scores 0.91-0.93, the paper-timed left-to-right at 71-86 %, the conflict-timed head-on at "
          "89-94 %, the lowest suite family at 69-77 %; its 1 and 2 M checkpoints meet 7 of the 8 targets "
          "(paper-timed left-to-right 80 and 72 %), the others 4-6. From 20 to 120 the weight raised the best "
          "checkpoint's left-to-right from 72 to 83 %; 240 adds nothing. Rejected. "
          "Row 34 (avoid-gsde-mirrorbc) carries the mirror image's skill over inside PPO: row 31's flags from its "
          "5 M checkpoint with an imitation term (`--bc-coef 0.05 --bc-grad-steps 20 --expert mirror "
          "--mirror-families cross-left --bc-label-steps 0`, training/imitation_term.py): after each PPO update "
          "20 minibatches fit the policy's mean to the frozen 5 M policy's mirrored action at every step of a "
          "cross-left scenario whose car is within 5 m on the ego's left (about 2 % of the steps), and PPO's "
          "objective holds the rest (row 22 fitted such labels without PPO). The left side moves at once and "
          "stays: paper-timed left-to-right 96-100 % and conflict-timed 98-100 %, the suite's cross-left 85-100 %, "
          "from the first checkpoint on, the first row to pass both timings from the left. The right side "
          "follows it into the mirror: paper-timed right-to-left 55-71 %, conflict-timed 72-85 %, cross-right "
          "58-68 %, and the staggered family (a car from the right, then one from the left) at 0-10 %, with "
          "head-on at 63-81 % and stopped at 59-73 %: scores 0.78-0.83 over 8 checkpoints to 7.1 M (22 min), no trend "
          "after 2 M, 2-4 of the 8 targets. In training the conflict suite's crossing families fell to 15-17 % within "
          "0.07 M samples and recovered to 50-73 % by 0.65 M (curriculum.csv). Stopped, rejected. (Its config.json "
          "says `bc_label_steps: 0`: it ran before the anchors below existed, when the field was ignored with "
          "the mirror teacher.) "
          "Row 35 (avoid-gsde-mirrorbc-anchor) is row 34 with anchors: every world also labelled with the "
          "teacher's own action at 4 random steps of each rollout (`--bc-label-steps 4`, about half the "
          "labels), to hold what is not mirrored. It collapses instead: in training the conflict suite's crossings "
          "from the right fall from 93 % at 0.07 M samples to 7 % at 0.65 M, those from the left from 46 to 4 % "
          "(curriculum.csv), and its 1-3 M "
          "checkpoints score 0.21-0.26 (conflict-timed 0-4 / 39-70 / 0-2 %, and on the paper-timed "
          "left-to-right the ego turns away, -2.3 to -2.6 m of progress). Likely why: the anchors contradict the mirrored labels "
          "on near-identical scans: a car on the ego's left at 5.1 m, or in a traffic or staggered episode, "
          "is labelled with the left turn, at 4.9 m in a cross-left episode with the mirrored right turn. "
          "Stopped at 4.5 M, rejected. "
          "Row 36 (avoid-gsde-mirrorbc-sides) is row 34 with anchors only where they are the mirror image of "
          "the mirrored labels: the teacher's own action at every step of a cross-right scenario whose car is "
          "within 5 m on the ego's right (`--anchor-families cross-right`, training/mirror.MirrorTeacher.anchored; "
          "43 % of the labels), so that both kinds of label turn with the crossing car's flow, each on its own "
          "side. It learns neither side: in training the conflict suite's crossings fall to 15-21 % within "
          "0.07 M samples and stay at 11-34 % from the left and 32-57 % from the right from 0.65 M on "
          "(curriculum.csv), and its 1-3 M checkpoints score 0.51-0.53 (conflict-timed 71-90 / 29-34 / 3-6 %, "
          "paper-timed 96-100 / 67-83 / 37-49 %, suite 44-46 % with its cross-left at 8-13 %), the imitation "
          "loss still at 7.0 at 4.7 M (row 34's: 0.6). 4.7 M samples in 13 min; stopped, rejected. Within "
          "these budgets the 2 x 64 network, moved this hard by the imitation term (20 minibatches after each "
          "update), does not hold a left-side and a right-side evasion at once. "
          "Row 37 (avoid-gsde-mirrorbc-weak) is row 34 with a fifth of the imitation steps (`--bc-grad-steps 4`; "
          "from this row on the mirrored labels are clipped to the car's steering range as in dagger.py: "
          "before, a label beyond the range still pulled a mean already past it further out, where the car "
          "does the same, and the agreement column of imitation.csv read such labels as disagreements). 11.6 M samples in 26 min (a median "
          "7.6 k samples/s): the left side is learnt more slowly and as well (from 2 M on paper-timed "
          "left-to-right 97-100 %, conflict-timed 94-100 %, the suite's cross-left 82-98 %; in training the "
          "paper-timed crossings from the left at 92-99 %, the steering within 0.05 rad of the labels on 78 % "
          "at the end), and the right side is lost as in row 34: conflict-timed right-to-left 7-48 %, "
          "paper-timed 58-88 %, the suite's cross-right 36-55 % and staggered 1-4 %; scores 0.71-0.79 over 9 "
          "checkpoints, at most 4 of the 8 targets. Stopped, rejected. Rows 34-37 show that the reflection of "
          "the right-side evasion can be taught to the left side (the first rows to pass both timings from the "
          "left) but, in this network and these budgets, at the cost of the evasion it came from. "
          "Row 38 (avoid-gsde-mirrorbc-wide) asks whether the network is too small to hold both: row 34 with 2 x 128 "
          "hidden units (`--hidden 128`; training/widen.py widens row 31's 5 M checkpoint with its function kept: each "
          "new unit copies one, and the outgoing weights are split at random between the two so that they train "
          "apart, tests/test_widen.py). 3.2 M samples in 17 min (a median 3.1 k samples/s, about half of row 34's): "
          "row 34's outcome, the left side passed (paper-timed left-to-right 98-100 %, conflict-timed 98-100 %) and "
          "the right side lost (conflict-timed right-to-left 21-61 %, paper-timed 50-76 %, staggered 3-6 %); scores "
          "0.75-0.82 over 4 checkpoints. Stopped, rejected: width is not what is missing. Its paths (the figure "
          "below, `racecav train paths`) show what the right side lost: it turns right at the intersection for the "
          "car from the right as for the car from the left, from about 2 m before the crossing, where its teacher "
          "(row 31, the second figure) turns left for both. "
          "The intersection's corners hide a crossing car until the ego is about 2 m from the crossing (the walls of "
          "docs/world.md). Before that a car coming from the left and one coming from the right give the same scan, "
          "and the teacher of rows 34-38 labels a car within 5 m on the ego's left whether the ego sees it or not. "
          "Row 39 (avoid-gsde-mirrorbc-seen) labels it only while it is in the ego's scan (`--mirror-seen`: "
          "FastWorld.seen_by_agent redoes the ego's scan without each car; tests/test_mirror.py checks it against plain "
          "line of sight). At 1 M samples it had stored 13.7 k labels, row 34 22.3 k (imitation.csv). 1.9 M samples "
          "in 7 min: the right side is lost as before (conflict-timed right-to-left 13-16 %, staggered 0-1 %; "
          "paper-timed left-to-right 94-95 %); scores 0.71-0.75. Rejected. Row 40 (avoid-gsde-mirrorbc-seen-sides) adds "
          "row 36's own-action labels for the cars seen on the right (`--anchor-families cross-right`), so that the "
          "two sides get opposite labels only on scans that tell them apart. It collapses as row 36 did: in "
          "training the crossings of every suite fall to 10-27 % within 0.07 M samples, including the traffic "
          "suite's, which has no labels (curriculum.csv); its checkpoints score 0.48-0.68 (the 2.0 M one passes "
          "the conflict-timed right-to-left 98 % and the left-to-right 0 %). 2.0 M samples in 7 min. Row 41 "
          "(avoid-gsde-mirrorbc-gentle) fits the same labels with an Adam of its own at a tenth of PPO's learning "
          "rate (`--bc-learning-rate 5e-6`): the same collapse (0.35-0.44 at 1-2.3 M; 2.3 M samples in 10 min). "
          "Rejected. The mirror table of row 31 (below) now also drives the teachers themselves in the fast world "
          "(`racecav train mirror`: row 31 until a car is near, or seen, on its left in a cross-left file, then its "
          "mirror image). Driven by the teachers, the crossings from the left fail: 3 % of the conflict suite's "
          "cross-left train files and 48 % of the paper-timed suite's (9 and 70 % with `--mirror-seen`), against 80 "
          "and 80 % for row 31 itself and 89 and 90 % for its mirror image. The mirror image's right turn works "
          "because it begins before the car is in view, where row 31 begins its left turn (about 2 m before the "
          "crossing, the second figure), and a turn begun to the left cannot be made into one to the right once "
          "the car appears. The labels of rows 34-41 ask for an evasion that a policy of the ego's view cannot "
          "start in time; the students learnt the one version they can, turning right at every intersection (the "
          "first figure), and lost the crossings from the right. With these corners the side of a crossing car is "
          "known only about 2 m before the crossing, so an evasion with the car's flow on both sides is not open "
          "to a policy of this view: one that passes both timings of both sides turns one way by default and "
          "tells the remaining case apart in the last 2 m (the probe below: 86 % of its held-out episodes at 2 m, "
          "96 % at 1.5 m). Row 42 (avoid-gsde-wide) is row 31 itself with 2 x 128 hidden units (`--hidden 128`, "
          "widened from row 31's 5 M checkpoint), plain PPO: 8.1 M samples in 43 min (a median 3.6 k samples/s, "
          "about half of row 31's): scores 0.88-0.93 over 9 checkpoints, the paper-timed left-to-right at 63-84 %, "
          "the conflict-timed head-on at 81-91 %, the suite's cross-left at 62-70 %; at most 6 of the 8 targets. "
          "Capacity alone does not move the weak cell either. Stopped, rejected.", "",
          "Rows 43-46 start again from row 31's 5 M checkpoint, with row 31's flags, one change each. In the "
          "paper-timed left-to-right row 31 starts its left turn about 2.8 m before the crossing, before the "
          "crossing car is in its scan (from about 2.1 m for a straight ego, FastWorld.seen_by_agent), turns "
          "into the crossing road and passes the car coming down it on the car's right: over 40 PyBullet "
          "trials (seeds 9000-9039, apart from the test and selection seeds) 35 pass with a median of 0.62 m between the centres (10th percentile "
          "0.51 m) and the 5 that fail touch at 0.36-0.47 m. Row 43 (avoid-gsde-hold) charges that early "
          "turn: `--hold-heading 30` (training/hold_heading.py) adds -30 per radian of heading away from the "
          "ego's road at each step of a scenario episode until a car has been in the ego's scan (latched per "
          "episode). 3.6 M samples in 15 min: scores 0.92-0.94 over 4 checkpoints, the paper-timed "
          "left-to-right at 73-88 %, the suite's cross-left at 62-70 %: row 31's range. The heading error "
          "before the car is in view is small (the turn becomes sharp only from about 2 m on, when the car "
          "is already seen), so the term changes little. Stopped, rejected. Row 44 (avoid-gsde-trackbc) "
          "teaches the straight pass directly: the imitation term of rows 34-41 with a new teacher, plain "
          "tracking of the ego's road at full throttle, on the steps of the paper-timed suite's cross-left "
          "files whose car is in the scan and near on the left (`--bc-coef 0.05 --bc-grad-steps 20 --expert "
          "track --mirror-families paper-timed/cross-left --mirror-seen --bc-label-steps 0`, "
          "training/mirror.MirrorTeacher with relabel track). The straight pass spreads to every crossing, "
          "as the mirrored turn did in rows 34-41: in training the conflict suite's crossings fall to "
          "8-18 % within 0.4 M samples and stay there; its 1 and 2 M checkpoints pass the paper-timed "
          "side scenarios (99-100 / 83-84 / 100 %) and none of the conflict-timed crossings (0-2 %), suite "
          "28 %: the planner-imitation outcome of row 13. 2.0 M samples in 11 min; stopped, rejected. "
          "Row 45 (avoid-gsde-clear) pays for the margin of every pass instead of only the touching ones: "
          "`--proximity-penalty 20` (training/proximity.py) adds -20 x (1.2 m - d) per step of a scenario "
          "episode where the nearest other car's centre is d < 1.2 m away. 6.1 M samples in 24 min: scores "
          "0.90-0.945 over 7 checkpoints (0.945 at 2 M, the highest of any row then: conflict-timed "
          "100 / 95 / 99 %, paper-timed 100 / 96 / 87 %, but the suite's cross-left at 61 %), the paper-timed "
          "left-to-right at 70-87 %, the lowest suite family at 61-77 %; 7 of the 8 targets at 4 and 6 M (paper-timed left-to-right 75 and 72 %). The pass "
          "does not widen (2 M: median 0.62 m between the centres over 40 trials, as row 31). Rejected. "
          "Row 46 (avoid-gsde-clear100) is row 45 at five times the weight (`--proximity-penalty 100`). "
          "15.6 M samples in 56 min (14 checkpoints evaluated): scores 0.92-0.948 (0.948 at 6 and 9 M: "
          "conflict-timed 100 / 86 / 99 %, paper-timed 100 / 99-100 / 90-91 %, suite 93 %, the highest score of"
          " any row), the lowest suite family at 64-74 %. The pass widens slowly (6 M: median 0.69 m between "
          "the centres, 10th percentile 0.54 m, 36 of 40 trials pass), and the paper-timed left-to-right rises "
          "with training: 73-91 % up to 10 M, 89-98 % from 11 M on (98 % at 14 and 15 M), the first row to hold"
          " it above 85 % for five checkpoints in a row. It trades again: from 11 M on the conflict-timed left-"
          "to-right falls to 86-89 % (95-100 % before) and the conflict-timed head-on stays at 84-96 %. At most"
          " 7 of the 8 targets (2 M), below row 31's pick on the paper-timed left-to-right; rejected for now, "
          "still moving when stopped: it resumes with `racecav train overtake --resume --run-dir runs/avoid-"
          "gsde-clear100 --steps 60e6` after copying training/checkpoints/avoid-gsde-clear100 to runs/. "
          "Resumed the next session to 54.1 M (evaluated at 16-30 M every 2 M, 32 and 33 M): the trade holds "
          "and drifts back. 16-18 M: paper-timed left-to-right 94-98 %, conflict-timed head-on 87-89 % and "
          "left-to-right 86-89 %. 20-33 M: paper-timed left-to-right 78-88 %, conflict-timed head-on 89-100 % "
          "and left-to-right 83-98 %. "
          "Suite 89-92 %, cross-left 64-74 %, scores 0.914-0.936, never above 7 of the 8 targets. Rejected. "
          "Row 47 (avoid-gsde-privileged) asks whether the trade is one of credit, not of view: row 31 from its "
          "5 M with a privileged critic (`--privileged-critic`, training/privileged.py: the critic also reads "
          "the nearest three cars' positions and velocities in the ego's frame, the ego's speed and the time "
          "left; the actor, the policy that ships, reads the scans as before). Its critic knows an episode's "
          "timing from the first step, so PPO's advantage of the decision at about 2 m is no longer the "
          "average over both timings. The critic uses what it is given: PPO's explained variance rises from "
          "row 31's 0.76 (mean over its 5-15 M) to 0.79, 0.84, 0.86 and 0.87 over 0-1, 1-3, 3-6 and 6-12 M. "
          "The actor does not move: 12.1 M samples in 34 min, scores 0.913-0.943 over 13 checkpoints, the "
          "paper-timed left-to-right at 75-92 %, the conflict-timed head-on at 86-94 %, suite 89-92 %, the "
          "lowest family at 64-79 %, at most 6 of the 8 targets. Sharper credit does not make the view tell "
          "the timings apart earlier; rejected. "
          "Row 48 (avoid-gsde-privileged-clear100) adds row 46's margin term to it (`--proximity-penalty 100`): "
          "14.4 M samples in 46 min, explained variance 0.86 (mean after 3 M), scores 0.888-0.934 over 15 "
          "checkpoints, the paper-timed left-to-right at 69-84 % (row 46 alone: 73-98 %), the conflict-timed "
          "head-on at 84-95 %, at most 6 of the 8 targets. Rejected. "
          "Row 49 (avoid-gsde-seenbc) teaches the policy of the probe's seeing planner (below): row 31 from "
          "its 5 M with the imitation term of rows 15 and 20 and the planner's labels restricted to what "
          "the policy has seen (`--bc-coef 0.05 --expert planner --expert-seen`, training/expert.py: plain "
          "tracking in a scenario episode until a car has returned a ray of the ego's scan, the planner "
          "from then on; traffic episodes keep the planner's labels). 2.3 M samples in 9 min: it collapses "
          "as rows 15 and 20 did. A third of its labels are manoeuvres and the policy agrees with 18-24 % "
          "of the newest ones (imitation.csv); in training every family falls to 15-54 % within 2 M "
          "samples (curriculum.csv); its checkpoints: conflict-timed 53-82 / 45-56 / 0-14 %, paper-timed "
          "91-98 / 82-91 / 20-39 %, suite 48-65 %, scores 0.52-0.63. The planner's manoeuvres after the "
          "car is in view are no easier to imitate than before: its exact prediction picks between "
          "nearly equal manoeuvres the scans do not tell apart. Stopped, rejected. "
          "Row 50 (avoid-gsde-holdtrack) asks for the same policy through the reward instead of labels: row 31 "
          "from its 5 M with `--hold-track 10` (training/hold_heading.py): -10 x (lateral offset (m) + heading "
          "error (rad) + (1 - T)) per step of a scenario episode until a car is in the view of a ghost, the "
          "ego moved onto its road's line at its progress (FastWorld.seen_by_agent with a pose), so a drift "
          "that shows the car early buys nothing (row 43's latch did pay for it). 37.8 M samples in 117 min "
          "(a median 5.6 k samples/s; stopped at 38.8 M). PPO's explained variance falls from row 31's 0.76 to 0.14-0.42 and "
          "stays there; the policy's departure before the ghost sees a car shrinks little (the term over "
          "256 fast paper-timed episodes at W = 30: median -76 per episode for row 31, -62 at 3 M, -56 at 36 M; "
          "90th percentile 1276, 784 and 1115, the episodes that turn up the crossing road); in training the "
          "paper-timed cross-left stays at 0.73-0.78 and falls to 0.64 by 38 M (curriculum.csv). "
          "Checkpoints (36 evaluated, 1-36 M): scores 0.82-0.926, the paper-timed left-to-right at 55-93 % "
          "(83 % at 1-2 M, above 85 % only at 13-15 M, where the paper-timed right-to-left falls to 71-96 %), "
          "the conflict-timed head-on at 57-90 %, suite 83-92 %, lowest family 51-72 %; at most 5 of the 8 "
          "targets. Rejected. "
          "Row 51 (avoid-gsde-holdtrack-priv) gives row 50's term row 47's privileged critic (`--privileged-critic`), "
          "which reads the cars the ghost's view is about to show, from row 31's 5 M. 7.4 M samples in 32 min "
          "(stopped at 2.2 M for rows 52-54, then resumed with `racecav train overtake --resume`). The critic "
          "follows the term better (explained variance 0.59 after 2.5 M; row 50: 0.14-0.42), and the actor "
          "moves as row 50's did, the wrong way: over 6 checkpoints (1-5 M) conflict-timed 92-100 / 70-87 / "
          "72-96 %, paper-timed 92-100 / 93-99 / 58-72 %, suite 84-91 %, lowest family 52-75 %, scores "
          "0.82-0.90 (row 50 over the same 1-5 M: 0.905-0.926), at most 5 of the 8 targets. Rejected. "
          "Row 52 (avoid-gsde-holdbc) labels the early turn away: row 31's flags from its 5 M with the imitation "
          "term and a new teacher (`--bc-coef 0.05 --bc-grad-steps 20 --expert hold --mirror-families "
          "braking,cross-left,cross-right,staggered,turning --bc-label-steps 4`, training/mirror.MirrorTeacher with "
          "relabel hold): full throttle and plain tracking of the ego's road at every step of an intersection "
          "scenario before any car has been in the ego's scan (latched per episode) while the ego is short of the "
          "crossing's centre, the frozen policy's own action at 4 random steps of each rollout. Why: row 31 turns left before "
          "the crossing car is in its scan (rows 43-46 above), and before a car is seen one label fits both "
          "timings and both sides. It collapses as rows 15, 20 and 49 did: in training the conflict "
          "suite's families fall to 8-45 % within 0.4 M samples (curriculum.csv; row 51 at the same point: "
          "78-97 %); about 80 % of its labels are relabelled steps, and the policy's steering agrees with 21-52 % "
          "of the newest (imitation.csv). Stopped at 0.6 M samples (3 min), rejected without a selection run. "
          "Row 53 (avoid-holddagger) fits the same labels without PPO, on every step the policy drives (DAgger, "
          "as row 22): `racecav train dagger --expert hold --mirror-families braking,cross-left,cross-right,staggered,"
          "turning --expert-share 0 --lr 1e-5 --grad-steps 100 --init-std 0.3` with row 31's env flags, from its 5 M. "
          "The frozen policy labels about 90 % of the steps with its own action, so the fit starts at its own "
          "function (the same command with a family that has no such steps, `--mirror-families stopped`, keeps the "
          "loss at 0.0 and the agreement at 1.0: the student's inputs and the teacher's are the same). 1.8 M "
          "samples in 6 min: the loss falls from 4.3 to 0.17-0.18, the steering agreement from 0.90 to 0.75-0.83 "
          "(progress.csv), and the straight approach does not come out of it. Its 0.5 M checkpoint's selection cells: conflict-timed 82 / 72 / 46 %, paper-timed 98 / 90 / "
          "68 %, suite 74 %, lowest family 43 %, score 0.75. Stopped, rejected: the labels before the car is in "
          "view move the answers after it as well. "
          "Row 54 (avoid-holddagger-ppo) is row 50 (`--hold-track 10`, row 31's flags) started from row 53's last "
          "checkpoint (1.8 M) instead of row 31's, as row 14 followed row 13: PPO to win back what the fit moved, "
          "the term to keep the straight approach. 6.1 M samples in 19 min: it recovers part of it (in training "
          "the conflict suite's families at 55-90 % after 2 M, curriculum.csv) but not row 31's level: over 4 "
          "checkpoints (1-4 M) conflict-timed 97-100 / 78-99 / 64-73 %, paper-timed 90-99 / 90-98 / 71-84 %, "
          "suite 82-87 %, lowest family 59-66 %, scores 0.84-0.89, at most 4 of the 8 targets. Stopped, rejected. "
          "Row 55 (avoid-gsde-open) asks whether row 31's early turn answers a car at all: row 31's flags from its "
          "5 M with a fourth training source, free intersections (`--scenarios conflicts,traffic,paper-timed,open`; "
          "`racecav suite generate --name open --n 20 --n-train 200 --seed 3`, common/data/suites/open.toml: the "
          "intersection with no other car and 4-5 s to get through it, docs/world.md). Through the services row 31 "
          "passes 1 % of that suite's test split (`racecav eval --suite open --controller drl-avoid "
          "--trials-per-scenario 5`; straight at full throttle 100 %, the paper's reversed policy 86 %): with no car "
          "in sight it turns up the crossing road as it does in front of one (the figure of row 31 on a free intersection, below). In "
          "training the open family stays at 2-3 % over 7.4 M samples (curriculum.csv), though the curriculum "
          "draws it most because it fails most; the free column of its three evaluated checkpoints is 1-3 % (row 31's "
          "5 M: 1 %, added with `racecav train select --run-dir training/checkpoints/avoid-gsde-flow120 --trials 100 "
          "--no-record`; the references: straight at full throttle 100 %, at 1 m/s 0 %). Selection: at 2 M "
          "conflict-timed 100 / 87 / 99 %, paper-timed 100 "
          "/ 91 / 85 %, suite 94 %, lowest family 70 %, score 0.936 (6 of the 8 targets); at 5 and 7.4 M 0.893 "
          "and 0.874, the paper-timed left-to-right down to 65 and 53 %. Stopped at 7.4 M (17 min), rejected. A free "
          "intersection alone does not pay for going straight: until the car is in view a free and an occupied "
          "intersection look the same, and the turn costs a few metres of progress on a free one against a "
          "collision it avoids on a conflict-timed one. "
          "Row 56 (avoid-gsde-open-hold) charges the turn where nothing answers it: row 55 + `--hold-track 10` "
          "(row 50's term; in an open episode no car ever comes into the ghost's view, so the term charges the "
          "whole departure from the road). 15.4 M samples in 39 min (stopped at 6.4 M, then resumed with "
          "`racecav train overtake --resume`). In training the open family rises slowly (2 % in the first 1 M, "
          "17 % at 4-6 M, 24-26 % from 8 M on) and the conflicts fall as it rises (the conflict suite's cross-left "
          "0.75 -> 0.56, cross-right 0.95 -> 0.76, staggered 0.80 -> 0.63; curriculum.csv; PPO's explained "
          "variance median 0.33 after 1 M, as row 50's). Its 16 checkpoints (1-15.4 M, free column 4-28 %): the "
          "paper-timed left-to-right climbs with the free column (59-73 % up to 3 M, 84-92 % at 5-14 M, 76 % at "
          "15.4 M) while the conflict-timed crossings and the suite give way (conflict-timed right-to-left 65-79 % "
          "and left-to-right 53-76 % from 12 M on, suite 76-87 % and lowest family 51-61 % from 4 M on); scores "
          "0.79-0.91, at most 6 of the 8 targets (1 M), 5 at 2 and 7 M. "
          "Stopped, rejected. Rows 55-56 show the trade from the other side: a policy of this view that goes "
          "straight through a free intersection also goes straight through the paper-timed crossings, and "
          "gives up the conflict-timed ones that only an early turn wins. "
          "Row 57 (avoid-gsde-open-hold-brake) gives row 56 a later answer than the turn: the brake "
          "(`--brake-below -0.5`, row 5's action; the fast world brakes at 9.7 m/s^2, about 0.4 m from "
          "2.7 m/s), from row 31's 5 M as row 56. A straight ego at full throttle has the conflict-timed crossing "
          "car from the left in its scan a median 2.86 m before the conflict point and passes most "
          "paper-timed ones before it sees them, and the privileged planner held straight to 2 m still passes "
          "both timings (the probe's tables below), so stopping for a car seen close to the crossing and "
          "driving on otherwise would pass both. PPO does not find it. "
          "8.0 M samples in 22 min; its 6 evaluated checkpoints (1-7 M): conflict-timed 93-99 / 72-87 / 60-83 %, "
          "paper-timed 96-99 / 92-99 / 59-76 %, suite 79-82 %, lowest family 51-66 %, free column 5-18 %, "
          "scores 0.82-0.84 (row 56 over the same checkpoints: 0.86-0.91), 2 of the 8 targets. Stopped, "
          "rejected. Row 58 (avoid-gsde-brake) gives the brake to row 31 alone (`--brake-below -0.5`, row 31's "
          "flags and mix, from its 5 M), without the free intersections and the charge that cost row 57 its "
          "conflicts. It starts lower (1-2 M: the paper-timed left-to-right at 40-44 %; with the brake, "
          "row 31's own actions below -0.5 stop the car where they used to coast) and scores 0.88-0.92 from "
          "4 M on (row 31's 5 M: 0.934). "
          "17.5 M samples in 47 min; its 16 evaluated checkpoints (1-17.5 M): conflict-timed 92-99 / 82-97 / "
          "83-96 %, paper-timed 95-100 / 81-100 / 40-87 %, suite 85-93 %, lowest family 62-82 % (82 % at 10 M, "
          "the highest of any row), free column 1-7 %, scores 0.83-0.92 (0.922 at 8 M: 98 / 94 / 94 | 97 / 95 / "
          "81 %; the table shows 16 M, in the same 0.05 step of the score with a higher suite); 7 of the 8 targets at 5 M (paper-timed left-to-right 71 %), at most 6 elsewhere. Stopped, "
          "rejected: the paper-timed left-to-right stays below row 31's 83 %. Started from a policy that "
          "hedges with a turn, neither row learns the straight approach with a late stop. "
          "Row 59 (avoid-gsde-from-dagger) starts row 31's recipe (its flags and mix, `--init-std 0.3` for "
          "gSDE) from the other end of the trade: row 14's last checkpoint (30.8 M), a policy that drives "
          "straight through the paper-timed crossings from the left and passes the conflict-timed ones but "
          "not the suite (its eval.csv at 30.8 M: paper-timed 100 / 65 / 99 %, conflict-timed 96 / 85 / 99 %, "
          "suite 74 %), instead of row 16's 4 M. Why: rows 57-58 started from a policy that already hedges "
          "with a turn; this one does not, and row 31's exploration, flow term and paper-timed cars are what "
          "gave row 31 the suite and the head-on. 19.5 M samples in 47 min (a median 7.4 k samples/s); its 16 "
          "evaluated checkpoints (1-17 M): paper-timed 89-100 / 62-92 / 73-100 % (the left-to-right at 85-100 % "
          "up to 15 M), free column 61-77 % (row 31: 1 %), but conflict-timed 51-83 / 66-89 / 67-88 %, suite "
          "57-77 %, lowest family 21-44 % (staggered: a car from the right, then one from the left), scores "
          "0.70-0.84 (best 0.843 at 7 M; the table shows 15 M, in the same 0.05 step of the score with a "
          "higher suite), at most 2 of the 8 targets. The recipe's new exploration first "
          "costs it the conflicts it had (1 M: 51 / 77 / 67 %), and over 17 M samples it wins back part of "
          "them while the suite stays below row 14's own. Stopped, rejected. From either end the trade holds: "
          "a policy that goes straight at the intersection does not get row 31's conflicts from row 31's "
          "recipe within 20 M samples, as row 31's does not get the straight pass. "
          "Row 60 (avoid-gsde-seen) removes the incentive for the early turn instead of charging it: row 31's "
          "flags and mix from its 5 M, with the conflict suite's train split cut to the files that the probe's "
          "seeing planner passes (held straight at full throttle until 2 control periods after a car first "
          "returned a ray of its ego's scan, then the privileged planner; kept if it passes at least 6 of 8 draws "
          "of the file's randomisation): `racecav train seen-filter --source conflicts --out "
          "runs/suites/conflicts-seen --draws 8` (training/seen_filter.py; 26 min on one core) keeps 1272 of "
          "the 1400 files: cross-left 150 of 200 (mean pass rate 76 %), cross-right 161, braking 171, staggered "
          "192, turning 198, head-on and stopped all; the same filter keeps every file of the traffic and "
          "paper-timed suites (all passed), so they stay as they were. Training: `--scenarios "
          "runs/suites/conflicts-seen,traffic,paper-timed`; selection still scores the whole conflict suite "
          "(suite.json's filtered_from; select.selection_cells). Why: a file that no reactive driver passes pays "
          "only for guessing; without those, a turn begun before the car is in view should earn nothing while the "
          "paper-timed files still charge it. It did not: 30.0 M samples in 57 min (a median 9.3 k samples/s); "
          "its 16 evaluated checkpoints (1-30 M): the paper-timed left-to-right falls from 80 % (1 M) to 44-67 % "
          "from 9 M on, and the paper-timed right-to-left with it (99-100 % up to 9 M, 65-74 % from 21 M on), while "
          "the suite's cross-left rises to 70-80 % (row 31's best: 69 %) and the conflict-timed cells hold (94-100 / "
          "86-93 / 94-100 %); scores 0.84-0.93, never above row 31's, at most 6 of the 8 targets. The policy "
          "does not reason from files it can no longer lose; the feasible crossings still reward starting the "
          "evasion early (it reacts slower than the privileged planner), and the mix it lost made the side "
          "crossings it kept the curriculum's hard ones. Stopped, rejected. "
          "Rows 61-65 force the straight approach in training instead of charging or imitating it. `--hold-until-seen` "
          "(TrainConfig.hold_until_seen, training/vec_env.FastVecEnv): in PPO's scenario episodes the ego is driven "
          "straight along its road at full throttle, whatever the policy's action, until a car has returned a ray of its "
          "scan or it is past its conflict point; from there the policy drives. Why: held so, the privileged planner "
          "passes the paper's six scenario files in the fast world (both timings of each side), freed at first sight "
          "or 4 control periods later (256 draws of each file's randomisation: 100 % of every file at first sight; 4 "
          "periods later 98 % of the conflict-timed right-to-left, 98 % of the conflict-timed left-to-right, 100 % "
          "of the others; `python -c \"from pathlib import Path; from racecav.training.seen_filter import "
          "pass_rates; print(pass_rates([Path('common/data/scenarios', n + '.toml') for n in ('right-to-left', "
          "'head-to-head', 'left-to-right', 'conflict-right-to-left', 'conflict-head-to-head', "
          "'conflict-left-to-right')], draws=256, delay=4, seed=0))\"`, delay=0 for first sight), so no conflict of the benchmark needs a turn begun before the car "
          "is in view, and in a held episode such a turn earns nothing. Row 61 (avoid-gsde-heldseen-nobc): row 31's "
          "flags and mix from its 5 M with `--hold-until-seen`. The answers to a car in view are learnt from the "
          "straight approach within 1-2 M samples (curriculum.csv at 7.5 M, held episodes: the conflict suite's "
          "cross-left 65-70 %, cross-right 84-89 %, staggered 83-90 %, braking 86-89 %, turning 88-92 %). But the "
          "steps before a car is in view no longer move the policy (its action there changes nothing, so PPO's "
          "gradient there is noise), and evaluated as it ships, driving those steps itself, it keeps row 31's turn: "
          "8.1 M samples in 16 min (a median 8.6 k samples/s), 5 checkpoints evaluated: conflict-timed 95-100 / "
          "83-97 / 89-98 %, paper-timed 100 / 97-100 / 60-73 %, suite 90-93 %, lowest family 66-75 %, free column "
          "0-1 %. Imitating the straight approach on the held steps (`--bc-coef --expert hold`; the labels read the "
          "env's latch) pulls the answers after the car is in view with it, as in rows 52-53: at `--bc-coef 0.05` from "
          "row 31's 5 M the held conflict families fell within 1 M samples (cross-right 54 -> 6-8 %, staggered "
          "54 -> 0-2 %, cross-left 48 -> 17-25 %; stopped at 4.3 M), and at `--bc-coef 0.01 --bc-grad-steps 5` from row "
          "61's 3 M more slowly (cross-left 68 -> 45 %, cross-right 89 -> 45 %, staggered 91 -> 53 % over 3.8 M "
          "samples) while the labels were still far from met (steering agreement 32-38 %); both stopped without "
          "evaluation, not in the table. Row 62 (avoid-gsde-heldseen-free) leaves the approach to the policy where a "
          "turn cannot pay: `--hold-families conflicts,traffic` holds the conflict and traffic suites only, and the "
          "policy drives the paper-timed files, which a straight fast ego passes, from the start; from row 61's 8 M "
          "(rows 62-64 and 65: training/checkpoints/avoid-gsde-heldseen-nobc/checkpoints/step_008003584.zip, committed; "
          "their config.json files name its runs/ path). "
          "9.0 M samples in 18 min; its 5 evaluated checkpoints: paper-timed left-to-right 44-76 % (76 % at 2 M, then "
          "44-60 %), conflict-timed left-to-right 70-92 %, suite 88-90 %, lowest family 54-70 %, free column 0-2 %, "
          "scores 0.85-0.91. Row 63 (avoid-gsde-heldseen-track) adds row 50's charge to the free episodes' approach "
          "(`--hold-track 10`; a held episode is straight and pays nothing): 9.6 M samples in 19 min, 7 evaluated "
          "checkpoints: paper-timed left-to-right 64-90 % (90 % at 2 M: conflict-timed 99 / 83 / 94 %, paper-timed "
          "100 / 94 / 90 %, suite 90 %, lowest family 70 %: 6 of the 8 targets), free column 0-2 %, scores 0.83-0.92. "
          "Row 64 (avoid-gsde-heldseen-track-lr) is row 63 at `--lr 1.5e-4`: 3.9 M samples in 8 min, 4 checkpoints: "
          "paper-timed left-to-right 78-86 %, conflict-timed left-to-right 66-83 %, scores 0.87-0.90. Row 65 "
          "(avoid-gsde-heldseen-noflow) is row 63 without the flow term (`--flow-reward 0`), the largest reward a turn "
          "up the crossing road can earn once a car is in view (120 per metre along a crossing car's travel, against "
          "18.5 per metre of progress): 10.9 M samples in 20 min, its 10 evaluated checkpoints "
          "(1-10.9 M): paper-timed left-to-right 62-90 %, conflict-timed 77-98 / 67-92 / 66-95 % (falling from 6 M "
          "on), suite 80-91 %, lowest family 56-70 %, free column 0-3 %, scores 0.81-0.93 (0.927 at 2 M, with the "
          "paper-timed left-to-right at 81 %). All rejected. "
          "Row 63's last checkpoint still turns up the crossing road to the left at a free intersection in all of 10 "
          "trials (the figure below), as row 31 does: within 10 M samples neither the paper-timed files nor the charge "
          "on them undo that habit of the intersection, and without the flow term (row 65) the answers to a car in "
          "view decay before it does. ", "",
          "![row 63 on a free intersection](img/training_paths_heldseen_track.png)", "",
          "Row 63's last checkpoint (9.6 M) on a free intersection: `racecav train paths --policy "
          "training/checkpoints/avoid-gsde-heldseen-track/latest.zip --scenarios "
          "runs/suites/open/test/intersection-0000.toml --trials 10 --out docs/img/training_paths_heldseen_track.png`.", "",
          "Rows 66-67 fit the straight approach with labels again, now with an anchor on the answers after the car is "
          "in view. `--anchor-seen` (TrainConfig.anchor_seen, training/mirror.MirrorTeacher.anchored): with `--expert "
          "hold`, every step of a labelled family after its hold ended (a car seen, or the ego past the crossing's "
          "centre) is labelled with the frozen `--init-from` policy's own action. Why: the two probes of rows 61-65 "
          "and rows 52-53 lost the answers to a car in view to the straight labels before it; anchored, those answers "
          "have labels of their own. Both start from row 61's 8 M, whose answers were learnt from the straight "
          "approach, with `--bc-coef 0.05 --expert hold --mirror-families braking,cross-left,cross-right,head-on,"
          "staggered,stopped,turning --bc-label-steps 0 --anchor-seen` and row 31's flags and mix. "
          "Row 66 (avoid-gsde-heldseen-anchor) keeps `--hold-until-seen`: 2.3 M samples in 5 min. The held conflict "
          "families drop in the first 0.1 M samples and then hold (curriculum.csv at 0.8 M: braking 73 %, cross-left "
          "53 %, cross-right 78 %, staggered 74 %; the probe without anchors at the same coefficient lost cross-right to "
          "6-8 % within 1 M); the labels are met (loss 1.68 -> 0.14 in 0.8 M samples, 11 % of them straight ones, "
          "imitation.csv). Its 3 evaluated checkpoints: conflict-timed 95-97 / 80-89 / 86-94 %, paper-timed 99-100 / "
          "85-92 / 54-67 %, suite 87-88 %, lowest family 66-74 %, free column 1-5 %, scores 0.85-0.88. Driven as it "
          "ships, it goes straight to about 2 m before the crossing and then turns up the crossing road as row 31 does "
          "(the figure below): the straight labels end where the held episodes' cars come into view, and past that "
          "point the anchors keep row 61's own turn, on scans that a free intersection shares. Row 67 "
          "(avoid-gsde-seenanchor) drops the override, so the straight labels fall on the approach the policy drives "
          "itself (the teacher keeps its own latch; DAgger's states): 3.2 M samples in 8 min; the labels are not met "
          "(steering agreement 0.72-0.80 on the newest after 1 M, imitation.csv), and over its 4 evaluated checkpoints the "
          "paper-timed left-to-right falls from 61 to 25 % (conflict-timed 96-100 / 79-84 / 83-95 %, paper-timed "
          "right-to-left and head-on 99-100 / 68-71 %, suite 78-85 %, lowest family 48-57 %, free column 3-7 %, scores "
          "0.80-0.81). Both rejected. "
          "Row 68 (avoid-dagger-ppo-brake) takes the other side of the trade: row 14's last checkpoint (30.8 M), which "
          "goes straight at the intersection and passes both timings of the crossings from the left, with the brake "
          "(`--brake-below -0.5`; rows 57-58 gave it to policies that already turn) and the paper-timed cars in its mix "
          "(`--scenarios conflicts,traffic,paper-timed`), row 14's other flags (`--lr 1.5e-4`, no gSDE, no flow "
          "term). Why: a straight approach that stops for a car seen close to the crossing passes both timings "
          "(row 57's reasoning), and this start does not have to unlearn a turn. 9.0 M samples in 14 min (a median "
          "10.8 k samples/s); in training the conflict suite's families stay where row 14 left them (cross-left "
          "47-76 %, cross-right 63-80 %, staggered 40-68 % after 1 M, curriculum.csv), and its 4 evaluated checkpoints "
          "(2-9 M): free column 88-93 %, paper-timed 95-100 / 36-82 / 87-99 %, conflict-timed 63-94 / 85-92 / "
          "63-96 %, suite 68-76 %, lowest family 48-59 %, scores 0.74-0.84. Rejected: the straight policy keeps the "
          "paper-timed crossings and the free intersection but not the suite or the head-on. Row 69 "
          "(avoid-dagger-ppo-brake-flow) adds the flow term (`--flow-reward 120`, rows 25-31: the evasion with a "
          "crossing car's flow, paid only while such a car is near, so an answer to a car and not to the "
          "intersection) from row 68's last checkpoint (its latest.zip, 9.0 M): 4.7 M samples in 7 min; it loses more "
          "than it gains: over its 3 evaluated checkpoints conflict-timed 16-57 / 59-85 / 56-76 %, paper-timed "
          "96-100 / 45-70 / 91-97 %, suite 64-69 %, lowest family 40-46 %, free column 68-76 %, scores 0.68-0.71. "
          "Rejected. "
          "Row 70 (avoid-gsde-heldthrough) is row 66 with the paper-timed crossings held straight to the conflict "
          "point, car in view or not (`--hold-through paper-timed/cross-left,paper-timed/cross-right`, "
          "TrainConfig.hold_through), from row 61's 8 M as row 66. Why: row 66's straight labels end where a car "
          "comes into view, about 2 m before the crossing, and the wide view has the paper-timed car from the left in "
          "its scan from there on; held through, that approach is labelled straight up to the crossing, car in view, "
          "while the conflict-timed car seen at the same point keeps row 61's answer (the anchors), so the labels "
          "themselves tell the two timings apart by what the scan shows. (A first start also held the paper-timed "
          "head-on files, `--hold-through paper-timed`; a straight ego meets that car, and its training success fell "
          "to 21 % within 1.7 M samples: stopped, not in the table.) 6.9 M samples in 15 min; the labels are fitted "
          "about as well as row 66's (loss 0.08-0.14, 11-12 % of them straight, steering agreement 0.56-0.89 on the "
          "newest, imitation.csv). Its 4 evaluated checkpoints (1-6.9 M): conflict-timed 92-100 / 81-88 / 82-90 %, "
          "paper-timed 99-100 / 87-92 / 60-72 %, suite 87-90 %, lowest family 67-72 %, free column 2-4 %, scores "
          "0.85-0.89. Rejected. Driven itself, it still leaves its road to the left from about 2.5 m before the "
          "crossing in the paper-timed left-to-right (the second figure below): the labels are met on the approach "
          "the override drives, not on the one the policy drives (which leaves it before the car is in view). "
          "Measured on the free intersection (`racecav train label-fit --policy P --scenarios open`, "
          "training/label_fit.py: 256 fast worlds of the open suite's train split, every step before a car is in view "
          "and short of the crossing, the share whose steering is within 0.1 of the labels' tracking steer, by the ego's "
          "distance to the crossing; held: the override drives, own: the policy), they are not met on the override's "
          "approach either, where it matters: from 3 m out, where the crossing cars come into view, the labels are "
          "followed far less than further out (the table). Row 71 (avoid-gsde-heldthrough-wide) asks whether the "
          "network is too small to tell that approach from one with a car in view (the anchors' scans): row 70's flags "
          "from its last checkpoint with `--hidden 256` (training/widen.py keeps its function). 2.5 M samples in 15 min "
          "(a median 2.8 k samples/s): the labels 2-3 m out are followed more on the held approach (26 -> 56 %), not on "
          "its own (13 -> 23 %, and 6 % from 2 m in); its 3 evaluated checkpoints: conflict-timed 98-100 / 79-80 / 93-96 %, "
          "paper-timed 100 / 82-90 / 62-66 %, suite 86-91 %, lowest family 59-70 %, free column 1-2 %, scores 0.86-0.89. "
          "Rejected. Row 72 (avoid-gsde-heldthrough-aux) gives the network a reason to encode the car instead: row "
          "70's flags from its last checkpoint, 64 units as shipped, with an auxiliary loss on the labelled steps "
          "(`--aux-seen 0.05`, TrainConfig.aux_seen, training/imitation_term.py): a training-only logistic head on the "
          "actor's last hidden layer predicts whether a car is in the ego's current scan (auxiliary tasks shape the "
          "shared layers, as in UNREAL, Jaderberg et al. 2017; the head is not part of the saved policy). 3.2 M samples in 7 min; "
          "the head reaches 0.91 accuracy where always answering \"no car\" scores 0.83 (17 % of the labelled "
          "steps have a car in the scan; the run's log), and the labels 2-3 m out are followed more on the held "
          "approach (26 -> 42 %), hardly on its own (13 -> 18 %; 5 % from 2 m in). Its 4 evaluated checkpoints: conflict-timed 94-100 / 72-83 / 81-85 %, paper-timed 100 / 79-83 / 71-78 %, suite 84-88 %, lowest family 56-61 %, free column 1-2 %, scores 0.85-0.88. Rejected. "
          "Rows 73-75 ask whether row 31's paper-timed left-to-right is a level or a fluctuation, and whether "
          "averaging steadies it. Row 73 (avoid-gsde-swa) is row 31's flags again from its 5 M checkpoint, checkpoints "
          "every 0.25 M (a replicate of row 31's own continuation, and the source of row 74): 6.0 M samples in 9 min. "
          "Its 6 evaluated checkpoints (1-6 M): conflict-timed 99-100 / 90-95 / 92-100 %, paper-timed 99-100 / 92-99 / "
          "68-88 %, suite 91-93 %, lowest family 61-70 %, free column 0-5 %, scores 0.92-0.94. Row 74 "
          "(avoid-gsde-swa-avg8) is stochastic weight averaging (Izmailov et al. 2018) of row 73: `racecav train "
          "average --run-dir runs/avoid-gsde-swa --window 8` (training/average.py) writes, for each of row 73's "
          "checkpoints from 2 M on, the mean of its last 8 checkpoints' weights (2 M samples of training) with "
          "their pooled observation normalisation, and select evaluates them checkpoint for checkpoint. Its 5 "
          "evaluated averages (2-6 M): conflict-timed 99-100 / 90-96 / 94-100 %, paper-timed 98-100 / 96-98 / 68-76 %, "
          "suite 92-93 %, lowest family 64-72 %, free column 0-3 %, scores 0.92-0.94. Row 75 (avoid-gsde-bigbatch) "
          "is row 31's flags from its 5 M with 4 times the rollout per update (`--n-steps 512 --batch-size 8192`: "
          "32768 samples per update, minibatches of 8192), less gradient noise per update: 8.0 M samples in 14 min; "
          "its 8 evaluated checkpoints (1-8 M): conflict-timed 99-100 / 86-95 / 97-100 %, paper-timed 99-100 / 92-100 / "
          "69-83 %, suite 90-92 %, lowest family 54-70 %, free column 2-4 %, scores 0.92-0.935. All three rejected: "
          "none meets more targets than row 31. What they measure: over the 14 checkpoints of rows 73 and 75 the "
          "paper-timed left-to-right has a mean of 76 % and a standard deviation of 5.3 points, where 100 trials "
          "at 76 % alone give 4.3: the checkpoints differ little more than the trials do, so row 31's recipe sits "
          "at about 76 % on these seeds (row 31's 5 M checkpoint, 83 % here and 84 % on the test seeds, is at the "
          "top of that spread), and the averages (mean 74 %) do not move it. Row 74's 6.0 M average meets 7 of 8 "
          "like row 31 at 5 M with a selection score 0.006 higher, well within the trials' noise, and was the "
          "targets' pick for a session; its paper-timed left-to-right, the target both miss, is 76 % against row "
          "31's 83 %. The targets now break such ties by the shortfall on the missed targets before the score "
          "(training/targets.ranked), which picks row 31 at 5 M again (its checkpoint stays committed in "
          "training/checkpoints/avoid-gsde-swa-avg8/checkpoints/). "
          "Row 76 (avoid-gsde-seenanchor-strong) is the step the last rows left open: row 67's labels on the "
          "policy's own approach (no override: straight tracking before a car is in view, the starting policy's "
          "own action after it, `--anchor-seen`), at ten times the imitation weight (`--bc-coef 0.5`), from row "
          "70's last checkpoint (so the anchors are row 70's answers). Why: rows 66-72 fit the labels where the "
          "override drives but not where the policy drives; with the labels on its own states and a weight that "
          "outweighs PPO's term, its own approach should follow them. 6.0 M samples in 13 min; steering agreement "
          "0.80-0.91 (imitation.csv). On the free intersection the labels are now met on its own approach more than "
          "3 m out (97 %, row 70: 62 %) and 2-3 m out (36 %, row 70: 13 %), but not from 2 m in (6 %): with no car "
          "anywhere, it still leaves its road there (the table). In training the conflict suite's crossings fall "
          "(cross-left 0.79 -> 0.54, staggered 0.88 -> 0.65, braking 0.94 -> 0.76 against row 73's curriculum.csv), "
          "and its 5 evaluated checkpoints (2-6 M): conflict-timed 99-100 / 64-74 / 83-97 %, paper-timed 100 / 66-72 / "
          "29-50 %, suite 81-84 %, lowest family 48-51 %, free column 1-4 %, scores 0.78-0.82. The turn moves closer "
          "to the crossing, where it loses the paper-timed left-to-right more, not less. Rejected. Row 77 "
          "(avoid-gsde-seenanchor-open) asks whether the turn 2 m out answers the intersection rather than a car: "
          "row 76's flags with the open suite's free intersections in the mix and labelled straight through "
          "(`--scenarios conflicts,traffic,paper-timed,open --mirror-families ...,intersection`: no car is ever in "
          "view there, so every step short of the crossing is labelled with the road's tracking steer), from row "
          "76's last checkpoint (its config.json names the runs/ path; the same file is "
          "training/checkpoints/avoid-gsde-seenanchor-strong/latest.zip). On the free intersection the labels are "
          "then met 2-3 m out on 57 % of its own steps and 18 % from 2 m in, and its free column rises to 39-50 %; "
          "in training the conflict suite's crossings collapse within 0.5 M samples (cross-left 0.42 at 0.5 M, 0.26-0.30 "
          "from 2 M on; braking 0.49-0.52, staggered 0.42-0.47; curriculum.csv). Stopped at 3.4 M samples (12 min); its 4 evaluated "
          "checkpoints (0.5-3.4 M): conflict-timed 80-98 / 62-76 / 87-94 %, paper-timed 87-100 / 59-68 / 69-91 %, "
          "suite 60-66 %, lowest family 25-33 %, free column 39-50 %, scores 0.73-0.78. Rejected. Together with "
          "row 14 (straight, suite 74 %) and rows 55-56, the measurement is plain: the suite's wins come from "
          "leaving the road at the intersection before any car is seen, and a policy taught not to do that "
          "loses them faster than it gains the paper-timed crossing from the left. "
          "Rows 78-79 try a manoeuvre that needs no turn before the car is in view: stop and look. `racecav train "
          "stop-probe` (training/stop_probe.py) drives the teacher of `--expert stop` (training/mirror.MirrorTeacher: "
          "full throttle on its road until 2.5 m before the conflict point, the brake until below 0.15 m/s, the brake "
          "again while a car in the ego's scan is within 0.8 m of the conflict point or within 3.5 m and closing on it, "
          "then straight on at full throttle; it reads the cars only where its scan shows them) by its own labels in "
          "the fast world, beside the non-evading references (straight at 1 m/s and at full throttle) on the same seeds "
          "(the selection seed; the families it does not drive go straight at full throttle): the table below. It passes both timings of the paper's "
          "crossings from either side, where the straight car loses every conflict-timed one, and 94 / 91 % of the "
          "suite's crossings from the left / right (row 31: 61-75 % of those from the left over its checkpoints); it "
          "does not answer a head-on, a stopped or a braking car (the steering evasion's families), passes a quarter of "
          "the staggered pairs and 83-89 % of the paper-timed suite's crossings (it waits for cars it would have passed "
          "ahead of, and some episodes end first). So the trade of rows 7-77 is not forced for the crossings: a "
          "side-neutral manoeuvre begun before any car is in view wins both timings. "
          "Rows 78-79 fit it in PPO: row 31's flags from its 5 M with the brake (`--brake-below -0.5`) and the imitation "
          "term with the stop teacher on the crossings of every suite (`--expert stop --mirror-families "
          "cross-left,cross-right --bc-label-steps 0`), the other families to PPO alone; row 78 (avoid-gsde-stoplook) at "
          "`--bc-coef 0.5`, row 79 (avoid-gsde-stoplook-strong) at 2.0. (Their first starts clipped the brake label to a "
          "coast: the imitation term bounded a_T to [0, 1] as for a car without a brake, training/dagger.action_bounds, "
          "so the policies learned to coast to the crossing and neither stopped nor turned; fixed and tested, restarted, "
          "not in the table.) Row 78: 10.3 M samples in 21 min (stopped there), steering and throttle agreement with the labels "
          "0.42 -> 0.97 (imitation.csv); row 79: 8.0 M in 17 min, 0.37 -> 0.95. Both learn the stop: driven in the fast "
          "world on the paper's four side files they stop 1.5-2 m before the crossing and wait, and they pass the "
          "conflict-timed crossings of both sides. Row 78's evaluated checkpoints from 2.5 M on (its 0.5 M one is "
          "between two habits: scores 0.31): conflict-timed 96-100 / 33-45 / 98-100 %, the suite's crossings from the "
          "left 80-90 % (more than any row before; row 31: 61-75 %), paper-timed 0-36 / 0-1 / 5-38 %, suite 41-51 % "
          "with the braking family at 0-5 % and turning at 15-26 %, free column 0-7 %, scores 0.43-0.48. Row 79's (2-8 M): "
          "conflict-timed 86-100 / 17-48 / 65-100 %, crossings from the left 56-84 %, paper-timed 0-4 / 0 / 2-9 %, "
          "suite 45-54 %, braking 0-6 %, turning 20-26 %, free column 0-2 %, scores 0.38-0.47. Why, from the same fast-world runs: after the stop they pull away at a "
          "throttle of 0.6-0.7 where the label says 1, so the paper's files (8 s, 5 m of progress) end before they are "
          "through (truncated, not a contact); and the stop before an intersection, learnt on the crossings, comes "
          "before every intersection (the scans do not tell the families apart there), where the braking, stopped, "
          "turning and head-on cars need the steering evasion that the stop replaced. Rejected. What is left for "
          "this lead: the go labelled to full throttle must be met (a larger weight on the throttle, or the "
          "episode's time counted in the reward), and the other families need their own answers after the stop "
          "(e.g. the stop teacher on every intersection family with the starting policy's own action once a "
          "car of a non-crossing family is in view, `--anchor-seen` style). "
          "Rows 80-83 drop the stop before the crossing: `--expert yield` (training/mirror.MirrorTeacher, relabel "
          "yield) labels full throttle on the road's tracking steer, and the brake only while a car in the ego's scan "
          "is within 0.8 m of the conflict point or within 3.5 m and closing on it. Its labels change only where the "
          "scan shows a car, so an intersection with no car in view is driven through at full throttle, as the "
          "paper-timed crossings need. Driven by its own labels (`racecav train stop-probe --expert yield`, the yield "
          "column of the table below) it passes all four of the paper's side files, 100 / 99 % of the conflict "
          "suite's crossings from the left / right, 75 % of its staggered pairs and 96 / 96 % of the paper-timed "
          "suite's crossings (the full-throttle car: 100 %). Row 80 (avoid-gsde-yield) fits it as rows 78-79 did: "
          "row 31's flags from its 5 M with `--brake-below -0.5 --bc-coef 0.5 --expert yield --mirror-families "
          "cross-left,cross-right,staggered --bc-label-steps 0`, the other families to PPO alone. 7.5 M samples in "
          "17 min (stopped there), steering agreement with the labels 0.22 -> 0.88 (imitation.csv). "
          "Its 4 evaluated checkpoints (2-7.5 M): conflict-timed 99-100 / 5-15 / 66-100 %, paper-timed 59-97 / 0 / "
          "44-96 %, suite 29-34 %, free column 60-87 %, scores 0.40-0.57. At 6 M both timings of both side "
          "crossings pass as in no row before (conflict-timed 100 / 100 %, paper-timed 97 / 96 %) and the suite's "
          "crossings from the left reach 90 % (97 % at 7.5 M), but every car it sees is answered with the brake: "
          "the head-on, stopped and braking families fall to 0-4 % (the fast world: it stops in front of a stopped "
          "car or an oncoming one and waits until the episode ends) and the head-to-head to 0 %. A start without "
          "the flow term (`--flow-reward 0`, 4.9 M samples, not evaluated) trained the same way (head-on 0.06-0.16, "
          "stopped 0.00 in curriculum.csv). Row 82 (avoid-gsde-yield-weak) is row 80 at a fifth of the imitation "
          "weight (`--bc-coef 0.1`), so that PPO keeps more of the other families: 3.5 M samples in 11 min, its 3 "
          "evaluated checkpoints: conflict-timed 80-99 / 11-14 / 28-93 %, paper-timed 37-60 / 0 / 53-73 %, suite "
          "24-37 % (stopped 0-1 %, head-on 31-36 %), free column 49-66 %, scores 0.31-0.50. The brake spreads to "
          "every car at this weight too. Row 81 (avoid-gsde-yield-anchor) gives the other families yield's "
          "approach and their own answers: `--anchor-families braking,head-on,stopped,turning` with yield "
          "(training/mirror.MirrorTeacher.anchored) labels their approach like yield's (tracking at full throttle "
          "until a car has been in the scan) and every step after it with the starting policy's own action (row 31's "
          "evasions; its coasts, a_T < 0 without a brake, are labelled as coasts, not as the run's brake: "
          "training/runs.source_env). Row 81's flags are row 80's plus the anchors, from row 31's 5 M: 10.0 M samples "
          "in 27 min; its 4 evaluated checkpoints (2.5-10 M): conflict-timed 6-11 / 58-69 / 8-91 %, paper-timed 85-100 / "
          "57-68 / 58-100 %, suite 29-52 % (crossings from the left 11-51 %), free column 79-97 %, scores 0.47-0.62. "
          "Row 83 (avoid-gsde-yield-keep) starts from row 80's 6 M, which has yield's answer, and labels the anchors "
          "with row 31's actions instead of its own (`--anchor-from "
          "training/checkpoints/avoid-gsde-flow120/checkpoints/step_005005312.zip`, TrainConfig.anchor_from): 13.1 M "
          "samples in 30 min; its 4 evaluated checkpoints (1.5-7.5 M): conflict-timed 5-17 / 37-60 / 35-68 %, "
          "paper-timed 99-100 / 40-46 / 93-100 %, suite 56-63 % with head-on 93-97 % and stopped 92-97 % back, "
          "crossings from the left 43-54 %, braking 18-28 %, free column 95-100 %, scores 0.56-0.64. (Two more starts "
          "of row 81, at `--bc-coef 2.0` and with turning not anchored, trained like it for 1.2 and 3.0 M samples and "
          "were stopped, not evaluated.) All four rejected. What they measure: the brake for a crossing car seen "
          "and the evasion of a car ahead, oncoming or turning are not told apart by these networks within these "
          "budgets. Alone, the yield labels make every car a reason to stop (rows 80, 82); anchored, the other "
          "families' answers (keep going and steer, about two thirds of the labels) win over the brake, and the "
          "conflict-timed crossings are lost (rows 81, 83). Row 80 at 6 M is the first checkpoint of the ablation "
          "that passes both timings of both side crossings (conflict-timed 100 / 100 %, paper-timed 97 / 96 %); "
          "the head-to-head and the suite are what it gives up. What is left for this "
          "lead: the two answers in one network. Row 84 (avoid-gsde-yield-balance) is row 83 with balanced "
          "imitation minibatches (`--bc-balance`, TrainConfig.bc_balance, training/imitation_term.minibatch: half "
          "yield's labels, half the anchors, where uniform draws gave the anchors about two thirds): 14.3 M samples in "
          "34 min (stopped for the session's end, resumable with `racecav train overtake --resume --run-dir "
          "runs/avoid-gsde-yield-balance --steps 30e6` after copying training/checkpoints/avoid-gsde-yield-balance "
          "to runs/). Its 8 evaluated checkpoints (0.5-14.3 M): conflict-timed 67-100 / 38-64 / 17-67 %, paper-timed "
          "92-100 / 26-75 / 93-100 %, suite 53-64 % (head-on 85-97 %, stopped 86-97 %, crossings from the left "
          "52-79 %, braking 10-18 %, turning 11-36 %), free column 96-100 %, scores 0.58-0.76, rising to the last "
          "(0.72 at 11 M, 0.76 at 14.3 M: conflict-timed 87 / 64 / 67 %, paper-timed 100 / 75 / 100 %). "
          "Resumed in the next session (the command above; its first save wrote into a record without a "
          "checkpoints/ folder and failed, fixed in training/runs.save_checkpoint and tested) to 24.3 M (another "
          "23 min, stopped for row 85): its 9 checkpoints from 14.5 M on: conflict-timed 35-74 / 56-74 / 47-98 %, "
          "paper-timed 98-100 / 69-85 / 99-100 %, suite 59-72 % (braking 15-27 %, turning 38-63 %), scores "
          "0.67-0.80, still rising slowly (0.78 at 22.5 M, 0.80 at 24.3 M: conflict-timed 62 / 68 / 95 %, "
          "paper-timed 98 / 81 / 100 %, suite 71 %). Rejected (below row 31). Row 85 (avoid-gsde-yield-release) "
          "gives the braking family yield's label until its car stops: a family named in both `--mirror-families` "
          "and `--anchor-families` is yield's (the brake while its car crosses) until a car in the ego's scan near "
          "the crossing has stopped, then anchored for the episode (training/mirror.MirrorTeacher, "
          "tests/test_mirror.py). Why: until it stops the braking family's car looks like a crossing one, and rows "
          "81-84 labelled those first steps with row 31's evasion where the crossings get the brake; a stopped car "
          "does not clear by waiting, so from there the evasion. Row 84's flags with `--mirror-families "
          "cross-left,cross-right,staggered,braking`, from row 84's 14.3 M (committed: "
          "training/checkpoints/avoid-gsde-yield-balance/checkpoints/step_014303232.zip): 30.0 M samples in 67 min. "
          "In training the crossings rise within 4 M samples (curriculum.csv: cross-left 0.68 -> 0.88, cross-right "
          "0.52 -> 0.74; at 30 M 0.85 / 0.79) and braking slowly (0.25 -> 0.49 at 30 M); turning stays at 0.33-0.55 (0.44 at 30 M). Its 16 "
          "evaluated checkpoints (1-30 M): conflict-timed 36-91 / 57-72 / 68-99 %, paper-timed 42-100 / 77-91 / "
          "93-100 %, suite 61-75 % (crossings from the left 75-98 %, from the right 67-86 %, braking 13-57 %, "
          "turning 34-43 %), free column 96-100 %, scores 0.65-0.835, the best of rows 80-85 (26 M: conflict-timed "
          "88 / 59 / 95 %, paper-timed 99 / 84 / 100 %, suite 75 % with the crossings from the left at 97 %, braking "
          "53 %, turning 38 %). Rejected (below row 31's 0.93). What is left: the turning family (row 31: 98-100 %; "
          "here 34-43 % from the first checkpoint to the last: its car turns across or into the ego's lane, and "
          "the yield teacher's conflict point, x = 0 on the ego's road, is not that family's), the head-to-head "
          "(57-72 % conflict-timed) and the swing of the conflict-timed right-to-left between neighbouring "
          "checkpoints (61-88 % from 20 M on).", "",
          "`racecav train stop-probe --scenarios common/data/scenarios/left-to-right.toml,"
          "common/data/scenarios/conflict-left-to-right.toml,common/data/scenarios/right-to-left.toml,"
          "common/data/scenarios/conflict-right-to-left.toml,common/data/scenarios/head-to-head.toml,"
          "common/data/scenarios/conflict-head-to-head.toml --families left-to-right,conflict-left-to-right,"
          "right-to-left,conflict-right-to-left --n 512`, then `--scenarios conflicts --families "
          "cross-left,cross-right,staggered,turning` and `--scenarios paper-timed` (1024 worlds each); the yield column "
          "is the same three commands with `--expert yield` (row 80's teacher):", "",
          "| scenario or family | episodes | stop and look | yield | straight 1 m/s | straight, full throttle |",
          "|---|---:|---:|---:|---:|---:|---:|",
          "| right-to-left (paper) | 84 | 100 % | 100 % | 0 % | 100 % |",
          "| head-to-head (paper; not driven) | 89 | 0 % | 0 % | 0 % | 0 % |",
          "| left-to-right (paper) | 94 | 100 % | 100 % | 0 % | 100 % |",
          "| conflict-right-to-left | 87 | 100 % | 100 % | 0 % | 0 % |",
          "| conflict-head-to-head (not driven) | 75 | 7 % | 7 % | 7 % | 7 % |",
          "| conflict-left-to-right | 83 | 100 % | 100 % | 0 % | 0 % |",
          "| conflicts/cross-left | 140 | 94 % | 100 % | 0 % | 1 % |",
          "| conflicts/cross-right | 128 | 91 % | 99 % | 0 % | 0 % |",
          "| conflicts/staggered | 134 | 24 % | 75 % | 0 % | 1 % |",
          "| conflicts/turning | 165 | 38 % | 4 % | 0 % | 1 % |",
          "| conflicts/braking, head-on, stopped (not driven) | 164, 152, 141 | 0 % | 0 % | 1, 0, 0 % | 0 % |",
          "| paper-timed/cross-left | 357 | 89 % | 96 % | 3 % | 100 % |",
          "| paper-timed/cross-right | 326 | 83 % | 96 % | 2 % | 100 % |", "",
          "Rows 86-90 widen the yield teacher until, driven by its own labels, it answers every family of the "
          "suite, and fit it. Row 85 was first resumed from 30 to 32 M samples (4 min, not evaluated) and its 32 M "
          "checkpoint committed (training/checkpoints/avoid-gsde-yield-release/checkpoints/step_032006144.zip): "
          "rows 86-89 start from it in a chain, each from its predecessor's last checkpoint (the same file as that "
          "run's committed latest.zip). Why the turning family stayed at 34-43 %: in the fast world (1024 worlds, "
          "the conflict suite's train split, selection seed) row 85 at 26 M passes 95 % of its left_across episodes"
          " (an oncoming car turns across the ego's road) and 3 % of its right_into ones (a car from the right "
          "turns into the ego's lane ahead of it and drives away at 0.5-2 m/s): it brakes while the car crosses, "
          "then goes at full throttle into the car's back. Row 31 passes 100 % of both by turning up the crossing "
          "road before the car is in view (the habit that loses the paper-timed left-to-right). The yield teacher "
          "itself passed 4 % of the turning family. Its new rules (training/mirror.MirrorTeacher, "
          "tests/test_mirror.py): (1) it follows a car in the ego's scan that is ahead in its lane and going its "
          "way (`_follow`: within 3 m ahead and 0.4 m aside, headings within 60 deg; the throttle of the car's "
          "speed plus 2 m/s per metre of gap beyond 0.8 m between centres, the brake when 0.2 m/s above it), "
          "wherever the ego is (past the crossing too); (2) a car along the ego's road (an oncoming one in the "
          "other lane, left_across before its turn) is busy only within 2 m of the crossing (within 3.5 m it made "
          "the ego wait for a car crawling up at 0.5 m/s, synchronised to the stopped ego, until the episode "
          "ended); (3) from row 88 on, it steers round a car in its scan that blocks its path, oncoming or stopped "
          "(`_dodge`: within 3.5 m or 1.6 s of closing, its extent across the road within the ego's path now or "
          "where the two will meet; the steer towards 0.35 m beside it on the side away from it, or the other side "
          "where the 2.4 m road has no room; full throttle), and a stopped car is no longer busy (it does not clear"
          " by waiting). Driven by its own labels, and on along the road at full throttle where they end (`racecav "
          "train stop-probe --expert yield`, which now drives on that way; the table below), the teacher of rows "
          "88-89 passes all six of the paper's files (99-100 %), 91-100 % of every conflict family but the "
          "staggered pairs (75 %), and 93-96 % of the paper-timed suite, where the straight cars pass 0-7 % of the "
          "conflict-timed cells. It reads only cars in the ego's scan, but it knows their speeds and headings "
          "exactly, which the policy has to read from two scans. Row 86 (avoid-gsde-yield-follow) is row 85's flags"
          " with rules (1)-(2) and the turning family yield's (`--mirror-families "
          "cross-left,cross-right,staggered,braking,turning --anchor-families braking,head-on,stopped`): 6.6 M "
          "samples in 16 min. In training turning rises (curriculum.csv: 0.44 at row 85's end, 0.55 at 2.4 M) and "
          "its 7 evaluated checkpoints (1-6.5 M) have turning at 54-69 % (row 85: 34-43 %), suite 68-76 %, but "
          "conflict-timed 12-56 / 44-57 / 68-89 % and paper-timed 66-100 / 48-71 / 79-99 %, scores 0.63-0.74. "
          "Driven in the fast world on the conflict-timed right-to-left, it stops for the car as the teacher does "
          "and then keeps braking for 5 s after the car has crossed and is driving away, so the episode ends first:"
          " from two scans 0.1 s apart a car crawling at 0.5 m/s moves by about one ray of the wide scan, and a car"
          " beside the road that is leaving looks like one that is coming. Row 87 (avoid-gsde-yield-stride) stacks "
          "the two scans 0.4 s apart (`--obs-stride 4`, EnvConfig.obs_stride; the policy service stacks the same "
          "way). The anchors (row 31) now see their own view, two consecutive scans, built from the env's scan "
          "history (FastVecEnv.stacked_view; before, an anchor policy saw the run's stack, tested in "
          "tests/test_mirror.py). 5.7 M samples in 15 min; its 5 evaluated checkpoints (1-5 M): conflict-timed "
          "69-92 / 38-52 / 99-100 %, paper-timed 93-100 / 18-46 / 93-100 %, suite 72-78 % (crossings from the left "
          "89-95 %, from the right 81-93 %, staggered 65-79 %, turning 48-58 %), free column 95-100 %, scores "
          "0.73-0.76: the crossings of both timings pass, the head-to-head does not (it drives at the oncoming car "
          "and slows a little; row 31 turns up the crossing road there). Row 88 (avoid-gsde-yield-dodge) is the "
          "teacher with rule (3) on every family and no anchors (`--mirror-families "
          "cross-left,cross-right,staggered,braking,turning,head-on,stopped`, no `--anchor-families`, "
          "`--anchor-from` or `--bc-balance`): 5.5 M samples in 14 min. Its 6 evaluated checkpoints (0.5-4.5 M): "
          "conflict-timed 79-99 / 27-45 / 94-100 %, paper-timed 92-100 / 1-21 / 98-100 %, suite 71-81 % (braking "
          "70-85 %, where rows 80-87 reached 57 % at most; crossings 90-97 / 87-94 %, head-on 45-76 %, stopped "
          "75-90 %, turning 52-65 %), free column 97-100 %, scores 0.70-0.76. The steer round the oncoming car is "
          "not learnt: in training the head-on family falls (curriculum.csv 0.68 at 2 M, 0.60 at 5.5 M) and the "
          "policy meets the paper's head-to-head car braking. Steering round a car is a few per cent of the labels,"
          " against the brake and the full throttle of every other labelled step. Row 89 "
          "(avoid-gsde-yield-dodge-balance) gives those steps half of each imitation minibatch (`--bc-balance`: "
          "with yield, the steps where its label steers round a car, MirrorTeacher.steered, are the second half, "
          "with any anchors; tests/test_mirror.py): 6.9 M samples in 17 min. In training the head-on family comes "
          "back (curriculum.csv 0.60 -> 0.88-0.91) and the stopped one with it (0.76 -> 0.90-0.96), turning falls "
          "(0.64 -> 0.29, 0.53 at 6.6 M). Its 8 evaluated checkpoints (0.5-6.9 M): conflict-timed 62-93 / 28-42 / "
          "64-96 %, paper-timed 79-100 / 21-61 / 77-100 %, suite 70-80 % (braking 61-89 %, crossings 70-82 / 71-90 "
          "%, head-on 83-92 %, staggered 65-76 %, stopped 89-96 %, turning 30-55 %), free column 78-99 %, scores "
          "0.62-0.775. The suite's head-on family passes, the paper's head-to-head files do not: in the fast world "
          "(100 episodes of each file) its last checkpoint passes 26 % of the paper-timed and 32 % of the "
          "conflict-timed head-to-head, steering 0.2-0.3 m aside where the teacher steers 0.6 m. The two files put "
          "the car dead ahead (offset 0 +- 0.05 m), where the teacher's side (away from the car) flipped with a few"
          " centimetres of offset, so the labels there taught the mean of both sides: straight on."
          " Row 90 (avoid-gsde-yield-keepright) makes that side one: a car within 0.25 m of dead ahead (the paper's"
          " offset and its randomisation) is passed on its right, the side of right-hand traffic "
          "(MirrorTeacher._dodge, KEEP_RIGHT_M; tests/test_mirror.py checks that every first steer round the "
          "paper's head-to-head car goes right); driven by its labels it still passes 92-99 % of the paper's "
          "head-to-head files (the column row 90 of the table below). Row 89's flags from its last checkpoint (6.9 "
          "M): 26.5 M samples in 64 min. Its 30 evaluated checkpoints (0.5-25 M): conflict-timed 50-96 / 13-52 / "
          "6-86 %, paper-timed 88-100 / 14-77 / 91-100 %, suite 66-79 % (braking 72-91 %, crossings 43-95 / 58-90 "
          "%, head-on 84-93 %, staggered 63-76 %, stopped 77-94 %, turning 30-53 %), free column 59-97 %, scores "
          "0.61-0.74 (the highest, 6 M: conflict-timed 95 / 23 / 81 %, paper-timed 98 / 48 / 99 %, suite 74 %). The "
          "paper-timed head-to-head reaches 68-77 % in the first 2.5 M samples, the best of the yield rows, and "
          "falls back to 14-53 % as the crossings from the left recover (43 -> 80-95 %): the steer to the right "
          "learnt for a car ahead spreads to the crossing car from the left in the first million samples and is "
          "unlearnt there only with the head-on answer. All five rows rejected (below row 31's 0.93). What they "
          "measure: a teacher that reads the cars' speeds and headings answers every family and both timings (its "
          "table), and PPO with these labels fits its families one at a time at this network's size and these "
          "budgets; the conflict-timed head-to-head stays at 13-52 % in every row from 86 on.", "",
          "Rows 91-95 fit the yield teacher without PPO (DAgger, as rows 13 and 53: `racecav train dagger`), after two "
          "fixes to what it is fitted to. Row 91 (avoid-yield-dagger64) is row 90's teacher on every family with row 90's"
          " env flags: `racecav train dagger --preset fast --world figure8 --heading reversed --n-obstacles 8 --driver "
          "centerline --scenarios conflicts,traffic,paper-timed --scenario-share 0.8 --curriculum --obs-stack 2 --obs-"
          "stride 4 --progress-reward 18.5 --lidar wide --brake-below -0.5 --lr 2e-4 --init-from "
          "training/checkpoints/avoid-gsde-yield-keepright/latest.zip --init-std 0.3 --hidden 64 --expert yield --mirror-"
          "families cross-left,cross-right,staggered,braking,turning,head-on,stopped --expert-share 0.3` (the policy "
          "drives 70 % of the episodes, the teacher 30 %; every step labelled, the newest 1.5 M fitted, 400 minibatches "
          "after each rollout). 2.2 M samples in 12 min; its 1 M checkpoint: conflict-timed 89 / 19 / 94 %, paper-timed "
          "100 / 4 / 100 %, suite 80 % (every family 71-92 %), score 0.72. The same at 2 x 128 (`--hidden 128`, widened "
          "as row 38) and both with `--bc-balance` (now a dagger flag too: half of each minibatch the steps where the "
          "teacher steers round a car, MirrorTeacher.steered) pass 3-28 % of the paper's two head-to-head files in the "
          "fast world (the policy driving 64 worlds of each file). Traced there, the labels along the "
          "policy's own path flip: the teacher's `_dodge` tested whether the car was in the path along the ego's current "
          "heading, so once the ego had turned a few degrees away the car no longer blocked, the label became the brake "
          "for a busy car with the tracking steer back towards it, and then the dodge again; a policy fitted to that "
          "steered back and forth in front of the car. Fix (training/mirror.py, tests/test_mirror.py): the test is made "
          "in the road's frame, a world that steered round a car at the last step keeps it blocking until the ego is 0.35"
          " + 0.1 m beside it (DODGE_HOLD_M), the heading of the manoeuvre is held within 0.25 rad of the road's "
          "(DODGE_MAX_RAD; at 0.6 the held manoeuvre overshot off the road: the paper's head-to-head fell to 4-11 %), it "
          "starts within 2.0 s of closing (was 1.6), and only a car along the road (|sin| of its heading < 0.2) counts as"
          " oncoming (a car turning across is a crossing one, waited for). Driven by its labels (the column rows 92-95 of"
          " the teacher table below) it passes all six paper files at 100 %, head-on 99 %, stopped 99 %, braking 95 %, "
          "turning 87 % (95 % before: the left_across car first looks like an oncoming one to steer round), staggered 75 "
          "%. With this teacher the 2 x 64 and 2 x 128 runs still passed the paper's head-to-head files in 3-28 % of the "
          "fast-world episodes, while they passed the suite's head-on family in 89-93 %: every head-on car of the "
          "training mix drives on the plain road, the paper's meets the ego at the intersection, where the crossing "
          "families teach waiting. The suite head-on-crossing (common/data/suites/head-on-crossing.toml, training only, "
          "`racecav suite generate --name head-on-crossing --n 20 --n-train 600 --seed 5`) puts head-on cars at the "
          "intersection, timed by the ego (head-on-x) and like the paper's Table 1 (head-on-x-paper); the teacher passes "
          "99 / 98 % of them, both straight cars 0 %. Row 92 (avoid-yield-crossing128) is row 91 at 2 x 128 with the "
          "fixed teacher, `--bc-balance` and that suite (`--scenarios conflicts,traffic,paper-timed,head-on-crossing`, "
          "`--mirror-families` + head-on-x,head-on-x-paper), in a chain of restarts from row 91's 2 x 128 twin (1.45 M, "
          "then 1.66 M with the balance, 1.81 M with the fixed teacher, then 1.24 M with the suite; 51 min in all). Its "
          "first 0.5 M with the suite: conflict-timed 93 / 88 / 94 %, paper-timed 98 / 97 / 100 %, suite 85 % (turning 65"
          " %, staggered 78 %), score 0.917: in the fast world the paper's head-to-head files went from 8-28 % to 93-95 %"
          " within those 0.5 M. Not shippable as it is: at 2 x 128 the service's fused kernel takes 10.3 us median "
          "against 6.4 us for 2 x 64 on the same loaded machine (the target is <= 10 us). Stopped at 1.24 M. Row 93 "
          "(avoid-yield-crossing64) is row 92 at 2 x 64, from row 91's 2 x 64 chain (2.2 M, 2.5 M with the balance, 1.76 "
          "M with the fixed teacher): 3.4 M samples with the suite in 19 min (53 min for the chain; the suite's head-on "
          "cars then drawn 0.5 m either side of the ego's path; row 94's at 0.25 m). Its 6 evaluated checkpoints (0.5-3 "
          "M): conflict-timed 84-96 / 82-93 / 85-95 %, paper-timed 94-100 / 94-98 / 93-100 %, suite 78-83 % (turning "
          "34-56 %, the lowest family of each), scores 0.88-0.92. Its 2 M checkpoint meets 6 of the 8 targets (conflict-"
          "timed 94 / 91 / 95 %, paper-timed 100 / 96 / 100 %; suite 83 %, turning 54 %), score 0.917, the first yield "
          "row to hold both timings of the paper's crossings and its head-to-head together. Traced in the fast world, its"
          " turning failures are both variants: behind the car that turned in ahead (right_into) it keeps 0.5-0.9 of "
          "throttle where the label asks for the car's speed, and the oncoming car that will turn across (left_across, "
          "0.5-0.6 m aside) it steers round like the suite's head-on cars at the crossing, 0.5 m aside and converging, "
          "which two scans 0.4 s apart do not tell from it (2-3 cm of drift). ",
          "Row 94 (avoid-yield-turn64) is row 93 from its 2 M checkpoint (committed) with the suite's head-on cars drawn "
          "in the ego's lane (0.25 m either side of its path: 0.5 m aside at the crossing is where the turning family's "
          "oncoming car drives), `--lr 1e-4` and the turning family drawn three times as often as its failure rate says "
          "(`--curriculum-boost conflicts/turning=3`): 4.1 M samples in 19 min. (A start with the first two of these from"
          " row 93's 1 M, 1.0 M samples in 5 min, was replaced by it before its first evaluation.) Its 5 evaluated "
          "checkpoints (0.5-3 M): conflict-timed 95-100 / 84-97 / 91-100 %, paper-timed 93-100 / 95-100 / 86-100 %, suite"
          " 82-87 % (turning 55-67 %, the lowest family of each), scores 0.91-0.94. Its 1 M checkpoint (committed) passes"
          " all six paper cells (conflict-timed 97 / 97 / 100 %, paper-timed 100 / 100 / 100 %), the suite 84 %, turning "
          "56 %: 6 of the 8 targets, score 0.939. Traced in the fast world, behind the oncoming car that will turn across"
          " (left_across) it holds 0.4 of throttle where the label is the full brake: the balanced minibatches give the "
          "steering round a car at full throttle half of every fit, ten times its share of the labels, and an oncoming "
          "car before its turn looks like one to steer round. Row 95 (avoid-yield-nobalance64) is row 94 from its 1 M "
          "checkpoint without `--bc-balance` (uniform minibatches: the labels round a car now agree along the policy's "
          "own path and the head-on cars are met at the crossing too, the two reasons the balance was needed): 3.2 M "
          "samples in 17 min, evaluated at 0.5 and 2 M (the run was stopped for the results table). 0.5 M: conflict-timed"
          " 97 / 95 / 99 %, paper-timed 99 / 94 / 100 %, suite 88 % (turning 81 %; the lowest family staggered, 74 %), "
          "score 0.941. 2 M: conflict-timed 96 / 98 / 99 %, paper-timed 100 / 96 / 99 %, suite 89 % (braking 87, "
          "crossings 100 / 93, head-on 97, staggered 74, stopped 93, turning 82 %), free column 99 %, score 0.950, the "
          "highest of any row. Each meets 7 of the 8 targets on the selection seeds, short of a paper-timed crossing's "
          "100 % by 1 trial of 100 (row 31's 5 M: the left-to-right by 17). ",
          "Kept; its 2 M checkpoint, the targets' pick (below; committed in training/checkpoints/avoid-yield-",
          "nobalance64/checkpoints/), is shipped as avoid from 2026-12-05 (`racecav train ship --run-dir runs/avoid-",
          "yield-nobalance64 --checkpoint 2007040 --name avoid`). Through the services on the test seeds and split ",
          "(docs/results.md of 2026-12-05, `racecav eval --table ... --resume`): conflict-timed 95 / 96 / 98 %, paper-",
          "timed 100 / 98 / 100 %, suite 89 % (braking 88, crossings 94 / 94, head-on 88, staggered 76, stopped 98, ",
          "turning 86 %), free intersection 94 %: every target as the table prints it. The paper-timed left-to-right is ",
          "199 of 200 (99.5 %, printed 100): its first trial (seed 0) waits for the crossing car and ends the 8 s 1.8 m ",
          "along its road, without contact, with the supervisor on and off alike.", "",
          "The yield teacher of rows 88-90 (rules 1-3; row 90 with its keep-right side) and of rows 92-95 (the dodge held in the road's frame: row 91's text), driven by its own labels: `racecav train stop-probe "
          "--expert yield --scenarios common/data/scenarios/left-to-right.toml,common/data/scenarios/conflict-left-"
          "to-right.toml,common/data/scenarios/right-to-left.toml,common/data/scenarios/conflict-right-to-left.toml"
          ",common/data/scenarios/head-to-head.toml,common/data/scenarios/conflict-head-to-head.toml --families lef"
          "t-to-right,conflict-left-to-right,right-to-left,conflict-right-to-left,head-to-head,conflict-head-to-hea"
          "d --n 512`, then `--scenarios conflicts --families "
          "cross-left,cross-right,staggered,braking,turning,head-on,stopped --n 1024` and `--scenarios paper-timed "
          "--families cross-left,cross-right,head-on --n 1024`, and for rows 92-95 `--scenarios head-on-crossing --families head-on-x,head-on-x-paper --n 512` (selection seed; the column of rows 80-85 is the "
          "table above, where that teacher drove the family):", "",
          "| scenario or family | episodes | yield, rows 80-85 | yield, rows 88-89 | yield, row 90 | yield, rows 92-95 | straight 1 m/s | straight, full throttle |",
          "|---|---:|---:|---:|---:|---:|---:|---:|",
          "| right-to-left (paper) | 84 | 100 % | 100 % | 100 % | 100 % | 0 % | 100 % |",
          "| head-to-head (paper) | 89 | not driven | 100 % | 99 % | 100 % | 0 % | 0 % |",
          "| left-to-right (paper) | 94 | 100 % | 100 % | 100 % | 100 % | 0 % | 100 % |",
          "| conflict-right-to-left | 87 | 100 % | 100 % | 100 % | 100 % | 0 % | 0 % |",
          "| conflict-head-to-head | 75 | not driven | 99 % | 92 % | 100 % | 7 % | 7 % |",
          "| conflict-left-to-right | 83 | 100 % | 100 % | 100 % | 100 % | 0 % | 0 % |",
          "| conflicts/braking | 164 | not driven | 99 % | 98 % | 95 % | 1 % | 0 % |",
          "| conflicts/cross-left | 140 | 100 % | 100 % | 100 % | 100 % | 0 % | 1 % |",
          "| conflicts/cross-right | 128 | 99 % | 99 % | 99 % | 99 % | 0 % | 0 % |",
          "| conflicts/head-on | 152 | not driven | 91 % | 91 % | 99 % | 0 % | 0 % |",
          "| conflicts/staggered | 134 | 75 % | 75 % | 75 % | 75 % | 0 % | 1 % |",
          "| conflicts/stopped | 141 | not driven | 99 % | 95 % | 99 % | 0 % | 0 % |",
          "| conflicts/turning | 165 | 4 % | 95 % | 95 % | 87 % | 0 % | 1 % |",
          "| paper-timed/cross-left | 357 | 96 % | 96 % | 96 % | 96 % | 3 % | 100 % |",
          "| paper-timed/cross-right | 326 | 96 % | 96 % | 96 % | 96 % | 2 % | 100 % |",
          "| paper-timed/head-on | 341 | not driven | 93 % | 94 % | 96 % | 0 % | 0 % |",
          "| head-on-crossing/head-on-x | 261 | not driven | not driven | not driven | 99 % | 0 % | 0 % |",
          "| head-on-crossing/head-on-x-paper | 251 | not driven | not driven | not driven | 98 % | 0 % | 0 % |", "",
          "| policy (free intersection, open suite) | held: x < -3 m | -3 to -2 m | -2 to 0 m | own: x < -3 m | -3 to -2 m | -2 to 0 m |",
          "|---|---:|---:|---:|---:|---:|---:|",
          "| row 31 at 5 M (the avoid shipped until 2026-12-05) | 6 % | 2 % | 7 % | 6 % | 2 % | 4 % |",
          "| row 61 at 8 M | 8 % | 1 % | 9 % | 8 % | 2 % | 5 % |",
          "| row 66 (2.3 M) | 79 % | 20 % | 26 % | 53 % | 7 % | 5 % |",
          "| row 70 (6.9 M) | 91 % | 26 % | 57 % | 62 % | 13 % | 6 % |",
          "| row 71 (2.5 M) | 96 % | 56 % | 79 % | 76 % | 23 % | 6 % |",
          "| row 72 (3.2 M) | 96 % | 42 % | 68 % | 77 % | 18 % | 5 % |",
          "| row 76 (6.0 M) | 98 % | 50 % | 60 % | 97 % | 36 % | 6 % |",
          "| row 77 (3.4 M) | 100 % | 79 % | 68 % | 99 % | 57 % | 18 % |",
          "| row 14 (30.8 M; goes straight, with more steering noise) | 46 % | 16 % | 39 % | 60 % | 10 % | 15 % |", "",
          "Policies: `avoid`, training/checkpoints/avoid-gsde-heldseen-nobc/checkpoints/step_008003584.zip, and the "
          "latest.zip of avoid-gsde-heldseen-anchor, avoid-gsde-heldthrough, avoid-gsde-heldthrough-wide, "
          "avoid-gsde-heldthrough-aux, avoid-gsde-seenanchor-strong, avoid-gsde-seenanchor-open and avoid-dagger-ppo in training/checkpoints/.", "",
          "![row 66 on a free intersection](img/training_paths_heldseen_anchor.png)", "",
          "Row 66's last checkpoint (2.3 M) on a free intersection: `racecav train paths --policy "
          "training/checkpoints/avoid-gsde-heldseen-anchor/latest.zip --scenarios "
          "runs/suites/open/test/intersection-0000.toml --trials 10 --out docs/img/training_paths_heldseen_anchor.png`.", "",
          "![row 70 on the paper-timed left-to-right](img/training_paths_heldthrough.png)", "",
          "Row 70's last checkpoint (6.9 M) on the paper-timed left-to-right: `racecav train paths --policy "
          "training/checkpoints/avoid-gsde-heldthrough/latest.zip --scenarios common/data/scenarios/left-to-right.toml "
          "--trials 10 --out docs/img/training_paths_heldthrough.png`.", ""]
    L += ["![the paths of row 38](img/training_paths_mirrorbc_wide.png)", "",
          "Row 38's last checkpoint: `racecav train paths --policy training/checkpoints/avoid-gsde-mirrorbc-wide/latest.zip "
          "--trials 10 --out docs/img/training_paths_mirrorbc_wide.png`.", "",
          "![the paths of row 31](img/training_paths_gsde_flow120.png)", "",
          "Row 31 at 5 M (the avoid shipped until 2026-12-05): `racecav train paths --policy "
          "training/checkpoints/avoid-gsde-flow120/checkpoints/step_005005312.zip --trials 10 --out "
          "docs/img/training_paths_gsde_flow120.png`.", "",
          "Row 31 at 5 M on three files of the open suite's test split, an intersection with no other car "
          "(`racecav suite generate --name open --n 20 --n-train 200 --seed 3`, then `racecav train paths --policy "
          "training/checkpoints/avoid-gsde-flow120/checkpoints/step_005005312.zip --scenarios "
          "runs/suites/open/test/intersection-0000.toml,runs/suites/open/test/intersection-0001.toml,"
          "runs/suites/open/test/intersection-0002.toml --trials 10 --out docs/img/training_paths_open.png`):", "",
          "![row 31 on a free intersection](img/training_paths_open.png)", ""]
    mirror_md = COMMITTED / "mirror-avoid.md"
    if mirror_md.is_file():
        L += ["### Row 16 and its mirror image", "",
              "The intersection families come in mirror pairs (a crossing from the left is a crossing from the "
              "right seen in a mirror; the suites draw both sides from the same ranges; only the staggered and "
              "turning families are one-sided). `racecav train mirror` (training/mirror.py) drives a policy and "
              "its mirror image, the same network on the mirrored scans with its steering negated, through the "
              "selection cells, beside the non-evading references on the same seeds. Row 16 at 4 M (shipped as "
              "avoid then) is lopsided: it passes both timings of the paper's crossing from its right (100 and 99 %) and half "
              "of the paper-timed one from its left (51 %), and its mirror image does the opposite (98 and 99 % "
              "from the left, 62 and 75 % from the right). The left side does not lack information in the view "
              "(the same scans, mirrored, suffice) but a skill the network has for the other side. Rows 22-24 "
              "try to carry it over, rows 25-26 to teach its evasion with the crossing car's flow.", "",
              mirror_md.read_text(), ""]
    mirror31_md = COMMITTED / "mirror-avoid-gsde-flow120.md"
    if mirror31_md.is_file():
        L += ["Row 31 at 5 M (the avoid shipped on 2026-12-02, the teacher of rows 34-41) is less lopsided and its "
              "mirror image a weaker teacher: it reflects onto the left 93 % of the paper-timed crossing from "
              "the right and 89 % of the conflict-timed one (row 16's: 98 and 99 %), against row 31's own 83 and 97 %.",
              "", mirror31_md.read_text(), ""]
    probe_md = COMMITTED / "probe-cross-left.md"
    if probe_md.is_file():
        L += ["### When the view tells the two timings apart", "",
              "Rows 10-12, 16-18 and 21 trade the paper-timed crossing from the left against the conflict-timed one. "
              "`racecav train probe` (training/probe.py) measures when the policy's view can tell them apart: "
              "row 7's 52 M checkpoint (the avoid shipped when it was measured) drives the suites' cross-left train files of both timings in the fast world; "
              "at the first step its ego is within 3, 2.5, 2 and 1.5 m of the conflict point, a fresh MLP of "
              "the policy's size (2 x 64 tanh) is fitted to tell the two timings apart from the scan there "
              "(alone, or with a scan 1-8 control periods older), on episodes matched on the ego's speed and "
              "balanced; its held-out accuracy is a lower bound. The policy turns the same way in both "
              "timings and commits between 2.5 m (5 deg) and 2 m (19 deg), while the view separates the "
              "timings only from about 2 m on (near chance at 3 m, about 70 % at 2.5 m): the difference "
              "arrives after the turn has begun. An older scan adds nothing the probe can read, at any "
              "distance and baseline (within 4 points of the newest scan alone), as rows 11, 12 and 17 (the "
              "longer baselines) found in training. What is left for "
              "these two families is a later decision (a policy that can still change its manoeuvre when "
              "the timings separate) or a manoeuvre that passes both timings, not more input. A later "
              "decision is possible in this world: the privileged planner (training/expert.py), held "
              "straight on its road at full throttle until its ego is 2 m from the conflict point and free "
              "from there, still passes every file of both timings (the third table; 256 worlds per cell), "
              "and only from 1.5 m does it fail most conflict-timed ones (24 % pass). At 2 m the view "
              "separates the timings at 82-86 %. Row 19 tried to train for that later decision with a reward "
              "term, and did not get it.", "",
              probe_md.read_text(), ""]
    seen_md = COMMITTED / "probe-cross-left-avoid.md"
    if seen_md.is_file():
        L += ["The same probe on row 31 at 5 M (the avoid shipped until 2026-12-05) adds a planner that can only answer what it "
              "sees: held straight at full throttle until a car first returns a ray of its ego's scan, and k "
              "control periods more (the scans a policy needs to judge the car's motion), free from there "
              "(`--seen-delays`, training/probe.seen_decision; the third table below). The paper-timed car "
              "crossing from the left stays hidden behind the corner from a straight fast ego until the "
              "ego is through the crossing (it is freed at the conflict point), and the straight pass wins "
              "all of them. The conflict-timed car comes out about 2.9 m before the crossing, and the "
              "planner freed then passes 77 % of them, 75 % after one or two periods (100-200 ms) and 59 % "
              "after four: the rest come out too late for any evasion, or not before the crossing at all. Row 31 passes 78 % of "
              "the paper-timed and 82 % of the conflict-timed ones here: more than the seeing planner on the "
              "conflicts, which only an evasion begun before the car is in view can do, and less on the paper "
              "timing, which such an evasion loses. So the trade of rows 7-48 is the price of evading what "
              "is not yet seen. The targets do not need it: a policy that drives straight at full throttle "
              "until it sees a car and then evades as the planner does would pass the paper-timed "
              "left-to-right (hidden from it), the conflict-timed one (the paper's file: in view from about 3 m, "
              "tests/test_train_probe.py) "
              "and about 75 % of the suite's crossings from the left (the lowest family's target: 70 %). "
              "Row 49 tried to teach that policy by imitating the seeing planner, and collapsed (above): what "
              "is missing is a way to learn it, not the information. The probe's own rows below use 1,024 worlds per source (about "
              "100 speed-matched episodes per class): too few for its accuracies, which the first table "
              "(8,192 worlds) measures.", "", seen_md.read_text(), ""]
    for run, *_ in rows:
        if (COMMITTED / run / "eval.png").is_file():
            img = REPO / "docs" / "img" / f"training_eval_{run}.png"
            shutil.copyfile(COMMITTED / run / "eval.png", img)
            L += [f"![{run} checkpoints](img/{img.name})", ""]
        if (COMMITTED / run / "curriculum.csv").is_file():
            img = _plot_curriculum(COMMITTED / run / "curriculum.csv", REPO / "docs" / "img" / f"training_curriculum_{run}.png")
            L += [f"{run}: each family's success in training (stochastic actions, its last 200 episodes), the "
                  "input of the curriculum's draw weights (`--curriculum`, training/vec_env.FamilyCurriculum):", "",
                  f"![{run} curriculum](img/{img.name})", ""]
    return "\n".join(L) + "\n"


def _plot_curriculum(csv_path: Path, img: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    with csv_path.open() as f:
        rows = list(csv.DictReader(f))
    fams = [k for k in rows[0] if k != "timesteps"]
    x = [int(r["timesteps"]) / 1e6 for r in rows]
    fig, ax = plt.subplots(figsize=(9, 4))
    for fam in fams:
        ax.plot(x, [100 * float(r[fam]) if r[fam] not in ("", "nan") else float("nan") for r in rows],
                label=fam, ls="-" if fam.startswith(fams[0].split("/")[0]) else "--")
    ax.set(xlabel="samples (M)", ylabel="training success (%)", ylim=(0, 100), title="curriculum: success per family")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, ncol=2, loc="lower right")
    fig.tight_layout()
    fig.savefig(img, dpi=100)
    plt.close(fig)
    return img
