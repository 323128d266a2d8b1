"""``racecav train sweep STAGE``: seeds (and a few values of one setting) of a training config on
Ray Tune (the ``ray`` extra, docs/cluster.md).

    racecav train sweep overtake --seeds 0,1,2 [--vary ent-coef=0,0.01] --steps 2e6 --out runs/sweep-x \\
        --train-args="--preset fast --scenarios conflicts ..." [--select-args="--trials 10"] [--ray ADDRESS]

Every trial is an ordinary run folder, OUT/<setting>seed<S>/, made by the project's own commands
in a child process: ``racecav train STAGE FLAGS --seed S [--VARY V] --steps N --run-dir DIR``
(``--resume`` when the folder holds a run), then ``racecav train select --run-dir DIR --no-record``.
The trial reports select's pick (best.json) to Tune: its selection score (``score`` for avoidance
runs, else the mean intersection success, else the held-out return) and checkpoint.

Resuming: a trial whose worker dies is restarted by Tune (``--retries``) and continues from its
folder's latest checkpoint; the whole command run again continues every unfinished trial the same
way, and a finished one (trial.json: same steps, same select arguments) only reports again. The
sweep writes OUT/sweep.csv (one row per trial), OUT/best.json and the link OUT/best to the best
trial's folder: ``racecav train select --run-dir OUT/best`` and ``racecav train ship --run-dir
OUT/best --checkpoint best`` take it from there. On a cluster OUT must be a folder every node
sees (a shared file system): the run folders are written where their trials run.
"""

from __future__ import annotations

import csv
import json
import os
import shlex
import subprocess
import sys
import time
from pathlib import Path

STAGES = ("racing", "overtake", "dagger")
OWN = ("--run-dir", "--resume", "--seed", "--steps")
"""Flags the sweep sets itself for every trial."""


def add_subcommands(sub, stage_parsers: dict) -> None:
    """``racecav train sweep``; ``stage_parsers``: the stages' own parsers, which check FLAGS."""
    p = sub.add_parser("sweep", help="seeds (and a few values of one setting) of a training run on Ray Tune, "
                       "each trial a resumable run folder, picked by racecav train select (training/sweep.py)")
    p.add_argument("sweep_stage", choices=STAGES, metavar="STAGE", help="racing | overtake | dagger")
    p.add_argument("--seeds", default="0,1", help="comma-separated training seeds (default 0,1)")
    p.add_argument("--vary", metavar="FLAG=V1,V2", help="also try these values of one of the stage's flags "
                   "(e.g. ent-coef=0,0.01): every seed with every value")
    p.add_argument("--steps", type=float, default=1e6, help="total samples of each trial (default 1e6)")
    p.add_argument("--out", type=Path, required=True, help="the sweep folder: one run folder per trial")
    p.add_argument("--select-args", default="", help="arguments of racecav train select for each trial "
                   "(e.g. \"--trials 10 --last 3\"; --run-dir and --no-record are set)")
    p.add_argument("--ray", nargs="?", const="", default="", metavar="ADDRESS",
                   help="the Ray cluster (host:port of `ray start --head`, or auto); default: a local Ray")
    p.add_argument("--cpus-per-trial", type=float, default=1.0,
                   help="CPUs each trial requests (training and selection run single-threaded)")
    p.add_argument("--retries", type=int, default=2, help="times Tune restarts a failed trial")
    p.add_argument("--no-progress", action="store_true", help="no Tune status table")
    p.add_argument("--train-args", default="", metavar="FLAGS", help="the stage's own flags, as `racecav train "
                   "STAGE` takes them (e.g. \"--preset fast --scenarios conflicts\"; --seed, --steps, --run-dir "
                   "and --resume are set by the sweep)")
    p.set_defaults(stage="sweep", stage_parsers=stage_parsers)


def _plan(args) -> tuple[list[dict], str]:
    """The trials' configs, or ([], why) for a bad set-up."""
    flags = shlex.split(args.train_args)
    own = [f for f in flags if f.split("=")[0] in OWN]
    if own:
        return [], f"--train-args: {own[0].split('=')[0]} is set by the sweep for every trial"
    try:
        seeds = [int(s) for s in args.seeds.split(",") if s.strip()]
    except ValueError:
        return [], f"--seeds {args.seeds!r}: comma-separated integers"
    if not seeds or len(set(seeds)) != len(seeds):
        return [], f"--seeds {args.seeds!r}: at least one seed, each once"
    values: list[str | None] = [None]
    flag = None
    if args.vary:
        name, eq, vals = args.vary.partition("=")
        values = [v.strip() for v in vals.split(",") if v.strip()]
        flag = "--" + name.strip().removeprefix("--")
        if not eq or not values or flag in OWN:
            return [], f"--vary {args.vary!r}: FLAG=V1,V2 with a flag of the stage other than {', '.join(OWN)}"
    if args.steps < 1 or args.cpus_per_trial <= 0 or args.retries < 0:
        return [], "--steps must be >= 1, --cpus-per-trial > 0, --retries >= 0"
    select = shlex.split(args.select_args)
    if any(a.split("=")[0] in ("--run-dir", "--no-record") for a in select):
        return [], "--select-args: --run-dir and --no-record are set by the sweep"
    stage_parser = args.stage_parsers[args.sweep_stage]
    trials = []
    for v in values:
        for s in seeds:
            extra = [] if flag is None else [flag, v]
            try:  # the stage's own parser names a bad flag or value (its usage line, exit 2)
                stage_parser.parse_args([*flags, *extra])
            except SystemExit:
                return [], f"--train-args/--vary: `racecav train {args.sweep_stage} {shlex.join([*flags, *extra])}` is refused"
            name = ("" if flag is None else f"{flag[2:]}{v}-") + f"seed{s}"
            record = args.out / name / "trial.json"
            if record.is_file() and json.loads(record.read_text()).get("flags") != [*flags, *extra]:
                return [], (f"{record.parent} holds a trial made with other flags "
                            f"({json.loads(record.read_text()).get('flags')}): use another --out")
            trials.append({"stage": args.sweep_stage, "flags": [*flags, *extra], "seed": s, "steps": int(args.steps),
                           "select": select, "run_dir": str((args.out / name).resolve()), "name": name,
                           "setting": None if flag is None else f"{flag[2:]}={v}"})
    return trials, ""


def selection_score(best: dict) -> tuple[float, str]:
    """(score, its column) of select's pick: an avoidance run's ``score``, else the mean
    intersection success, else the held-out return (a racing run selected with --no-intersection)."""
    for col in ("score", "intersection_success", "env_return"):
        if best.get(col) not in (None, ""):
            return float(best[col]), col
    raise ValueError(f"best.json names no selection score ({sorted(best)})")


def _racecav(args: list[str], log: Path) -> None:
    """``racecav ARGS`` in its own process group, which stops itself if this worker dies."""
    from racecav.common import procs

    p = procs.start(args, dict(os.environ), log)
    try:
        rc = p.wait()
    finally:
        procs.stop(p)
    if rc != 0:
        raise RuntimeError(f"racecav {' '.join(args[:2])} exited with code {rc}; see {log}")


def run_trial(config: dict) -> dict:
    """One trial, resumable: train (or continue) to ``steps``, select, return the metrics."""
    run_dir = Path(config["run_dir"])
    run_dir.mkdir(parents=True, exist_ok=True)
    record = run_dir / "trial.json"
    want = {"steps": config["steps"], "select": config["select"], "flags": config["flags"]}
    if record.is_file():
        done = json.loads(record.read_text())
        latest = json.loads((run_dir / "latest.json").read_text()) if (run_dir / "latest.json").is_file() else {}
        if "score" in done and {k: done.get(k) for k in want} == want and latest.get("timesteps", 0) >= config["steps"]:
            return done
    record.write_text(json.dumps(want, indent=1) + "\n")  # its flags from the start: _plan refuses others
    train = ["train", config["stage"], *config["flags"], "--seed", str(config["seed"]), "--steps",
             str(config["steps"]), "--run-dir", str(run_dir), "--no-progress"]
    if (run_dir / "latest.zip").is_file():  # an earlier attempt's checkpoint: continue from it
        train.append("--resume")
    t0 = time.monotonic()
    _racecav(train, run_dir / "train.log")
    _racecav(["train", "select", "--run-dir", str(run_dir), "--no-record", "--no-progress", *config["select"]],
             run_dir / "select.log")
    best = json.loads((run_dir / "best.json").read_text())
    score, col = selection_score(best)
    done = {**want, "score": score, "score_column": col, "checkpoint": best["checkpoint"],
            "seed": config["seed"], "setting": config["setting"], "run_dir": str(run_dir),
            "wall_s": round(time.monotonic() - t0, 1)}
    record.write_text(json.dumps(done, indent=1) + "\n")
    return done


def _tune_trial(config: dict) -> None:
    from ray import tune

    done = run_trial(config["trial"])
    tune.report({k: v for k, v in done.items() if k not in ("select", "flags")})  # Tune logs scalars and text


def run(args, cfg) -> int:
    trials, why = _plan(args)
    if why:
        print(f"racecav train sweep: {why}", file=sys.stderr)
        return 2
    from racecav.common import cluster

    try:
        cluster.init(args.ray)
        from ray import tune
    except ImportError:
        print("racecav train sweep: ray is not installed (pip install 'racecav[ray]')", file=sys.stderr)
        return 2
    except ConnectionError as e:
        print(f"racecav train sweep: {e}", file=sys.stderr)
        return 2
    out = args.out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    trainable = tune.with_resources(_tune_trial, {"cpu": args.cpus_per_trial})
    tuner = tune.Tuner(
        trainable, param_space={"trial": tune.grid_search(trials)},
        tune_config=tune.TuneConfig(metric="score", mode="max", trial_name_creator=lambda t: t.config["trial"]["name"],
                                    trial_dirname_creator=lambda t: t.config["trial"]["name"]),
        run_config=tune.RunConfig(name=time.strftime("tune-%Y%m%dT%H%M%S"), storage_path=str(out / "tune"),
                                  failure_config=tune.FailureConfig(max_failures=args.retries),
                                  verbose=0 if args.no_progress else 1))
    grid = tuner.fit()
    rows = []
    for r in grid:
        t = (r.config or {}).get("trial", {})
        m = r.metrics or {}
        rows.append({"trial": t.get("name"), "seed": t.get("seed"), "setting": t.get("setting") or "",
                     "score": m.get("score", ""), "score_column": m.get("score_column", ""),
                     "checkpoint": m.get("checkpoint", ""), "run_dir": t.get("run_dir"),
                     "error": "" if r.error is None else str(r.error).splitlines()[0][:200]})
    rows.sort(key=lambda r: r["trial"] or "")
    with (out / "sweep.csv").open("w", newline="") as f:
        w = csv.DictWriter(f, list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    ok = [r for r in rows if r["score"] != "" and not r["error"]]
    for r in rows:
        print(f"  {r['trial']}: " + (f"score {r['score']:.4g} ({r['score_column']}), {r['checkpoint']}"
                                     if r in ok else f"FAILED {r['error']}"))
    if not ok:
        print(f"racecav train sweep: no trial finished; see the logs in {out}/*/", file=sys.stderr)
        return 1
    best = max(ok, key=lambda r: r["score"])
    (out / "best.json").write_text(json.dumps(best, indent=1) + "\n")
    link = out / "best"
    if link.is_symlink() or link.exists():
        link.unlink()
    link.symlink_to(Path(best["run_dir"]).relative_to(out) if Path(best["run_dir"]).is_relative_to(out)
                    else Path(best["run_dir"]))
    print(f"best trial: {best['trial']} (score {best['score']:.4g}, {best['checkpoint']}); "
          f"racecav train ship --run-dir {link} --checkpoint best --name NAME")
    if len(ok) < len(rows):
        print(f"racecav train sweep: {len(rows) - len(ok)} trial(s) failed; run the same command again to "
              "continue them", file=sys.stderr)
        return 1
    return 0
