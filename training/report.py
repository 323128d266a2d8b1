"""``racecav train report`` and ``racecav train paths``: docs/training.md and the path plots.

- ``report``: >= 100 PyBullet trials per scenario for each shipped policy (evaluation/inprocess.py,
  report seeds), stored in the policies' JSON metadata, their path plots, the learning curves;
  then writes docs/training.md with :func:`render`, which reads only committed files: the prose
  (docs/training_notes.md, docs/training_ablation.md), the ablation's rows (training/ablation.csv),
  the run records (training/checkpoints/) and the metadata. tests/test_training_doc.py checks the
  page is exactly what it writes.
- ``paths``: a policy's ego and obstacle paths through the intersection scenarios.
"""

from __future__ import annotations

import csv
import json
import logging
import time
from pathlib import Path

from racecav.common import registry
from racecav.evaluation.inprocess import REPORT_SEED, SELECT_SEED, eval_scenario
from racecav.evaluation.plots import plot_paths
from racecav.training import targets
from racecav.training.runs import (COMMITTED, EXPERIMENTS_COMMIT, REFERENCES_CSV, REMOVED_AT, REPO, load_run_config,
                                   run_dir_of)

log = logging.getLogger("racecav.train")

SCENARIOS = registry.PAPER_SCENARIOS
CONFLICT_SCENARIOS = registry.CONFLICT_SCENARIOS
PAPER_HW = {k.removeprefix("drl-"): tuple(round(100 * v) for v in r) for k, r in registry.PAPER_TABLE1.items()}
DOC = REPO / "docs" / "training.md"
NOTES = REPO / "docs" / "training_notes.md"
ABLATION_PROSE = REPO / "docs" / "training_ablation.md"
ABLATION_CSV = REPO / "training" / "ablation.csv"
TABLE_MARK = "{{ablation_table}}"
"""Where docs/training_ablation.md takes the table drawn from training/ablation.csv."""
REPORT_POLICIES = ("racing", "default", "reversed", "avoid")


def report(args, cfg) -> int:
    import torch

    from racecav.common.policy import MODELS_DIR, load_policy

    torch.set_num_threads(1)
    names = [n for n in args.policies.split(",") if (MODELS_DIR / f"{n}.npz").is_file()]
    for name in names:
        meta_path = MODELS_DIR / f"{name}.json"
        meta = json.loads(meta_path.read_text())
        stored = meta.get("evaluation", {})
        if (args.reuse and stored.get("trials") == args.trials
                and (REPO / "docs" / "img" / f"training_paths_{name}.png").is_file()):
            continue
        pol = load_policy(name)
        res = {"trials": args.trials, "seed0": REPORT_SEED, "backend": "pybullet"}
        paths = {}
        for sc in SCENARIOS:
            r = eval_scenario(pol, sc, args.trials, REPORT_SEED, record=10)
            paths[sc] = r.pop("paths")
            res[sc] = r
            log.info("%s %s: %s", name, sc, r)
        plot_paths(name, paths, REPO / "docs" / "img" / f"training_paths_{name}.png")
        res["measured"] = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
        meta["evaluation"] = res
        meta_path.write_text(json.dumps(meta, indent=2, sort_keys=True, default=str) + "\n")
    plot_curves()
    DOC.write_text(render(names))
    print(f"wrote {DOC}")
    return 0


def render(names=REPORT_POLICIES) -> str:
    """docs/training.md from committed files only (no evaluation, no figure drawn)."""
    from racecav.common.policy import MODELS_DIR

    results = {}
    for name in names:
        meta_path = MODELS_DIR / f"{name}.json"
        if meta_path.is_file() and (ev := json.loads(meta_path.read_text()).get("evaluation")):
            results[name] = ev
    return (_markdown(results, curve_stats()) + recipes_markdown() + ablation_markdown()
            + targets.section(COMMITTED, json.loads((MODELS_DIR / "avoid.json").read_text())) + flags_markdown())


def draw_paths(args, cfg) -> int:
    """``racecav train paths``: a policy's ego and obstacle paths through intersection scenarios."""
    import torch

    torch.set_num_threads(1)
    try:
        from racecav.training.policy_io import named_policy

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
    out = plot_paths(f"{run.name}/{spec.stem}" if spec.suffix == ".zip" else spec.stem, paths, args.out)
    print(f"wrote {out}: {', '.join(rates)} of {args.trials} trials (selection seeds)")
    return 0


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


def curve_stats() -> dict[str, dict]:
    """Per committed run: samples, wall time, median throughput and its TrainConfig."""
    import numpy as np

    stats = {}
    for name, r in _runs().items():
        sps = [float(x_["samples_per_s"]) for x_ in r["rows"][1:] if x_.get("samples_per_s")]
        last = r["rows"][-1] if r["rows"] else {}
        stats[name] = {"samples": int(float(last.get("timesteps", 0))), "wall_s": float(last.get("wall_s") or 0),
                       "samples_per_s_median": float(np.median(sps)) if sps else float("nan"),
                       "config": r["config"]}
    return stats


def plot_curves() -> None:
    """docs/img/training_curves.png: the committed runs' learning curves."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    runs = _runs()
    if not runs:
        return
    fig, ax = plt.subplots(1, 2, figsize=(13, 7))
    colors = plt.get_cmap("tab20").colors
    for k, (name, r) in enumerate(runs.items()):
        rows = [x for x in r["rows"] if x.get("ep_rew_mean") not in ("", None)]
        x = [int(float(x["timesteps"])) / 1e6 for x in rows]
        # 20 colours x 2 line styles: 30-odd runs stay distinguishable
        style = {"color": colors[k % len(colors)], "linestyle": "-" if k < len(colors) else "--", "lw": 1}
        ax[0].plot(x, [float(x_["ep_rew_mean"]) for x_ in rows], label=name, **style)
        ax[1].plot(x, [float(x_["ep_len_mean"]) * 0.1 for x_ in rows], label=name, **style)
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


def _markdown(results: dict, curves: dict) -> str:
    L = ["# Training the racing, default, reversed-heading and avoid policies",
         "",
         "Generated by `racecav train report` (do not edit by hand): the text is docs/training_notes.md and",
         "docs/training_ablation.md, the ablation's rows training/ablation.csv, the numbers the committed",
         "run records (training/checkpoints/) and the shipped policies' metadata (common/data/policies/).",
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
        if (REPO / "docs" / "img" / f"training_eval_{name}.png").is_file():
            L += [f"Checkpoint evaluation of `{name}` (`racecav train select`):", "",
                  f"![{name} checkpoints](img/training_eval_{name}.png)", ""]
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
    L += ["", "Measured by `racecav train report` at the times in the policies' metadata: "
          + ", ".join(f"{n} {r.get('measured', '?')}" for n, r in results.items()) + ".", ""]
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




def recipes_markdown() -> str:
    """The recipes (training/recipes/NAME.toml): each stage's command, start, samples and what it
    does; with a committed record (training/recipes/NAME/manifest.json) the samples done and the
    wall time of each stage on this machine."""
    from racecav.training.recipe import RECIPES, load_recipe, names

    L = ["", "## Recipes", "",
         "A shipped policy is rebuilt by its recipe: `racecav train recipe NAME` (training/recipe.py) runs the",
         "stages of training/recipes/NAME.toml in order, each a run of `racecav train racing|overtake|dagger` with",
         "its full settings (a TrainConfig, common/config.py) and its start: a committed zip named by its sha256,",
         "or an earlier stage's final checkpoint. A stage runs in runs/recipes/NAME/STAGE and resumes where it",
         "stopped, after its config.json was checked against the recipe; `--chunk-steps N` stops after N more",
         "samples (a checkpoint first), so a long recipe runs in chunks across sessions (a DAgger stage keeps its",
         "aggregate, optimiser and rng beside its latest checkpoint, runs/.../dagger-state.pt, up to ~2 GB, and goes",
         "on with them; until 2026-12-07 it restarted an empty aggregate: the avoid recipe's refine stage is",
         "recorded from a run with its aggregate kept). Each stage counts its",
         "samples from its own start. runs/recipes/NAME/manifest.json records each stage's start and its digest,",
         "the digests of its settings and of its scenario files (a generated suite is made again on a fresh clone),",
         "samples, wall time and the final checkpoint's digest; `racecav train recipe NAME --record` copies it, the",
         "stage records and each finished stage's final weights to training/recipes/NAME/ (committed), from which",
         "a later stage starts on a fresh clone.", ""]
    for name in names():
        recipe = load_recipe(RECIPES / f"{name}.toml", configs=False)
        mpath = RECIPES / name / "manifest.json"
        done = {e["name"]: e for e in json.loads(mpath.read_text())["stages"]} if mpath.is_file() else None
        L += [f"### `racecav train recipe {name}`", "", " ".join(recipe.description.split()), "",
              "| stage | command | start | ends at (samples) | what |"
              + (" samples done | wall time |" if done else ""),
              "|---|---|---|---:|---|" + ("---:|---:|" if done else "")]
        for st in recipe.stages:
            start = f"stage `{st.after}`" if st.after else f"`{st.start}` (sha256 `{st.start_sha256[:12]}`)"
            row = f"| {st.name} | {st.command} | {start} | {st.steps / 1e6:g} M | {' '.join(st.what.split())} |"
            if done:
                e = done.get(st.name, {})
                row += (f" {e['samples'] / 1e6:.2f} M | {_hours(e.get('wall_s', 0))} |" if e.get("samples")
                        else " - | - |")
            L.append(row)
        total = sum(e.get("wall_s", 0) for e in done.values()) if done else 0
        L += ["", (f"Samples and wall time: training/recipes/{name}/manifest.json, {_hours(total)} in all (one "
                   "training process on the shared 2-core box)." if done else
                   f"Not run yet: no record in training/recipes/{name}/ (`racecav train recipe {name} --record`)."),
              "", shipped_from(name), ""]
    return "\n".join(L)


def _hours(wall_s: float) -> str:
    return f"{wall_s / 60:.0f} min" if wall_s < 7200 else f"{wall_s / 3600:.1f} h"


def shipped_from(name: str) -> str:
    """Whether the shipped policy ``name`` is the output of the recipe ``name`` (its metadata's
    ``recipe``, written by ``racecav train ship --recipe``), and of this version of the file."""
    from racecav.common.policy import MODELS_DIR
    from racecav.training.recipe import RECIPES, sha256

    meta_path = MODELS_DIR / f"{name}.json"
    rec = json.loads(meta_path.read_text()).get("recipe") if meta_path.is_file() else None
    if not rec or rec.get("name") != name:
        return f"The shipped `{name}` policy was not built by this recipe."
    same = rec.get("sha256") == sha256(RECIPES / f"{name}.toml")
    return (f"The shipped `{name}` policy is stage `{rec.get('stage')}` of "
            + ("this recipe" if same else f"an earlier version of this file (sha256 `{str(rec.get('sha256'))[:12]}`)")
            + f" (common/data/policies/{name}.json).")


def ablation_rows() -> list[dict]:
    """training/ablation.csv: one row per run of the avoid ablation, in order."""
    with ABLATION_CSV.open() as f:
        return list(csv.DictReader(f))


def ablation_table(rows: list[dict]) -> str:
    """The ablation's table: each row's change, best checkpoint and its selection scores, then the
    two non-evading references on the same cells and seeds (training/checkpoints/references.csv)."""
    fams = [k.removeprefix("suite_") for k in rows[0] if k.startswith("suite_") and k != "suite_success"]
    pct = lambda v: f"{100 * float(v):.0f}" if v not in (None, "") else "-"  # noqa: E731
    sides = lambda r, scs: " / ".join(pct(r.get(f"{s}_success")) for s in scs)  # noqa: E731
    L = ["| # | run | verdict | change | best checkpoint | score | score of the last checkpoint | suite | "
         + " | ".join(fams) + " | conflict R-L / H-H / L-R | paper R-L / H-H / L-R | free |",
         "|---:|---|---|---|---|---:|---:|---:|" + "---:|" * len(fams) + "---|---|---:|"]
    for r in rows:
        change = f"on {r['base']}: {r['change']}" if r["base"] else r["change"]
        best = f"{int(r['best_checkpoint'].split('_')[1].split('.')[0]) / 1e6:.1f} M" if r["best_checkpoint"] else "-"
        L.append(f"| {r['row']} | {r['run']} | {r['verdict']} | {change} | {best} | {pct(r['score'])} | "
                 f"{pct(r['last_score'])} | {pct(r['suite_success'])} | "
                 + " | ".join(pct(r.get(f"suite_{f}")) for f in fams)
                 + f" | {sides(r, CONFLICT_SCENARIOS)} | {sides(r, SCENARIOS)} | {pct(r['free_success'])} |")
    if REFERENCES_CSV.is_file():
        with REFERENCES_CSV.open() as f:
            for r in csv.DictReader(f):
                L.append(f"| | *{r['reference']}* | reference | never evades (a_T = {float(r['a_throttle']):.2f}, "
                         f"steering 0) | - | {pct(r['score'])} | - | {pct(r['suite_success'])} | "
                         + " | ".join(pct(r.get(f"suite_{f}") or 0) for f in fams)
                         + f" | {sides(r, CONFLICT_SCENARIOS)} | {sides(r, SCENARIOS)} | {pct(r.get('free_success'))} |")
    return "\n".join(L)


def ablation_markdown() -> str:
    """The avoid ablation: docs/training_ablation.md with its table drawn from training/ablation.csv,
    then the committed runs' curriculum figures (their checkpoint figures are under Runs)."""
    rows = ablation_rows()
    prose = ABLATION_PROSE.read_text()
    if prose.count(TABLE_MARK) != 1:
        raise ValueError(f"{ABLATION_PROSE}: needs {TABLE_MARK} once (where the table goes)")
    L = ["", prose.replace(TABLE_MARK, ablation_table(rows)).strip(), ""]
    for r in rows:
        run = r["run"]
        if (REPO / "docs" / "img" / f"training_curriculum_{run}.png").is_file():
            L += [f"{run}: each family's success in training (stochastic actions, its last 200 episodes), the "
                  "input of the curriculum's draw weights (`--curriculum`, training/vec_env.FamilyCurriculum):", "",
                  f"![{run} curriculum](img/training_curriculum_{run}.png)", ""]
    return "\n".join(L) + "\n"


def flags_markdown() -> str:
    """The flags of ``racecav train racing|overtake|dagger``, from TrainConfig and EnvConfig, with
    their defaults as ``racecav train overtake --help`` prints them."""
    from racecav.common.config import EnvConfig, TrainConfig
    from racecav.training.flags import DAGGER_FLAGS, ENV_FLAGS, TRAIN_FLAGS, stage_defaults

    paper, fast = stage_defaults("overtake", "paper"), stage_defaults("overtake", "fast")

    def row(model, name, flag, key):
        doc = " ".join((model.model_fields[name].description or "").split()).replace("|", "\\|")
        shown = lambda v: "{}" if v == {} else v  # noqa: E731
        return f"| `{flag}` | {shown(paper[key])} | {shown(fast[key]) if fast[key] != paper[key] else ''} | {doc} |"

    L = ["", "## Flags of `racecav train racing|overtake|dagger`", "",
         "Generated from TrainConfig and EnvConfig (common/config.py); `racecav train STAGE --help` prints the "
         "same, with each stage's defaults (the racing stage: no obstacle cars, centerline traffic). A run records "
         "them all in its config.json. The ablation's other settings are gone from training/ (an old "
         f"config.json that turns one on is refused, naming the commit where its code is: {EXPERIMENTS_COMMIT}"
         + "".join(f", {k} {c}" for k, c in REMOVED_AT.items()) + ").", "",
         "| flag | default (overtake) | --preset fast | what it sets |", "|---|---|---|---|"]
    L += [row(TrainConfig, n, "--" + n.replace("_", "-"), n) for n in TRAIN_FLAGS]
    L += [row(EnvConfig, n, flag, f"env.{n}") for n, flag in ENV_FLAGS.items()]
    L += ["", "`racecav train dagger` only:", "", "| flag | default | --preset fast | what it sets |", "|---|---|---|---|"]
    L += [row(TrainConfig, n, "--" + n.replace("_", "-"), n) for n in DAGGER_FLAGS]
    return "\n".join(L) + "\n"
