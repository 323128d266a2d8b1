"""``racecav train select|references``: checkpoint evaluation on the selection split.

- ``select --run-dir DIR``: every checkpoint (or the last ``--last K``) of a run is evaluated on
  held-out seeds of its own training env (fast world: mean return, contact rate) and on the three
  intersection scenarios in-process on the PyBullet backend (evaluation/inprocess.py; success =
  no contact and ego progress >= the scenario's min_progress_m). Writes ``DIR/eval.csv`` and
  ``DIR/eval.png`` and names the best: highest mean intersection success in 5-point steps (finer
  differences are noise at 30 trials per scenario), then the highest held-out return, then fewer
  intersection contacts (the paper picked its checkpoints by evaluation too). Selection seeds
  (SELECT_SEED + k) differ from the report's (REPORT_SEED + k), so the reported rates are not the
  ones the pick was made on.
- ``references``: the non-evading references (the registry's scripted and full-throttle
  controllers, in-process) scored on the same selection split as an avoidance run's checkpoints
  -> training/checkpoints/references.csv, the ablation table's reference rows.

``racecav train ship`` (training/ship.py), ``report`` and ``paths`` (training/report.py) are
defined here too, with the other subcommands' arguments.
"""

from __future__ import annotations

import csv
import json
import logging
import math
from pathlib import Path

from racecav.common import registry
from racecav.evaluation.inprocess import (SELECT_SEED, eval_env, eval_scenario, eval_suite_fast,
                                          reference_drivers)
from racecav.training.policy_io import policy_from_checkpoint
from racecav.training.runs import (COMMITTED, REFERENCES_CSV, checkpoints, load_run_config, save_run_record,
                                   step_of)

log = logging.getLogger("racecav.train")

SCENARIOS = registry.PAPER_SCENARIOS
CONFLICT_SCENARIOS = registry.CONFLICT_SCENARIOS
SUCCESS_RESOLUTION = 0.05


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
    p.add_argument("--recipe", metavar="NAME", help="the recipe that built the run (training/recipes/NAME.toml; "
                   "--run-dir is one of its stages): the metadata names it and its digest")
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
    if args.train_cmd == "ship":
        from racecav.training.ship import ship

        return ship(args, cfg)
    if args.train_cmd in ("report", "paths"):
        from racecav.training import report

        return {"report": report.report, "paths": report.draw_paths}[args.train_cmd](args, cfg)
    return {"select": select, "references": references}[args.train_cmd](args, cfg)


# ----------------------------------------------------------------------------------- selection
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
    """``spec`` if that suite's train split is generated, else None with a warning (the column is
    skipped; `racecav eval --table` writes only the test split of a suite it generates)."""
    if not spec:
        return None
    from racecav.common.scenario import open_suite

    try:
        open_suite(spec).files("train")
    except (FileNotFoundError, ValueError) as e:
        log.warning("free-road column skipped (%s); the open suite is generated by racecav suite generate "
                    "--name open --n 20 --n-train 200 --seed 3 (docs/world.md)", e)
        return None
    return spec


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


def select(args, cfg) -> int:
    import torch
    from tqdm import tqdm

    torch.set_num_threads(1)
    run_dir = args.run_dir
    tc, _record = load_run_config(run_dir)
    cks = checkpoints(run_dir)
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
        n = step_of(ck)
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
