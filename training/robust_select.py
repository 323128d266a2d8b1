"""``racecav train robust-select``: candidate policies on the selection seeds under perturbations.

Whether a candidate holds up under perturbations is decided here, on the selection split and
never on the table's test seeds (ablation rows 96-97: training under randomised perturbations,
measured with it and removed): each candidate (a policy .npz, e.g. a
checkpoint shipped to a scratch name) runs the conflict-timed scenarios through the services
(`racecav eval`, lockstep, so the latency perturbations are charged where the car has them) under
the ideal world and each perturbation, and the paper-timed ones in the ideal world (what it must
not lose). Seeds SELECT_SEED + k, as ``racecav train select``. Writes one CSV row per cell and a
markdown table with 95 % Wilson intervals (docs/robustness.md, "Training under randomised
perturbations").
"""

from __future__ import annotations

import csv
import json
import subprocess
import tempfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from racecav.evaluation.inprocess import SELECT_SEED

CONFLICT = ("conflict-right-to-left", "conflict-head-to-head", "conflict-left-to-right")
PAPER = ("right-to-left", "head-to-head", "left-to-right")
PERTURBATIONS = "s2-nominal,s2-pessimistic,worn-car,slippery-floor,late-computer,latency_s=0.1"
FIELDS = ["model", "perturbation", "scenario", "successes", "trials"]
REFERENCES = {"no evasion, 1 m/s": "scripted", "no evasion, full throttle": "full-throttle"}
"""The two non-evading references (registry controllers), run on the same seeds and cells."""


def add_subcommands(sub) -> None:
    p = sub.add_parser("robust-select", help="candidate policies on the selection seeds under perturbations "
                       "(through the services): does training under perturbations pay?")
    p.add_argument("--models", required=True, help="NAME=PATH.npz,... (the shipped avoid: "
                   "avoid=common/data/policies/avoid.npz)")
    p.add_argument("--perturbations", default=PERTURBATIONS, help="presets or key=value settings, each a column "
                   f"besides the ideal world; ';' between them when one has several keys (default {PERTURBATIONS})")
    p.add_argument("--trials", type=int, default=20, help="trials per scenario and cell")
    p.add_argument("--jobs", type=int, default=2, help="evaluations at once (one core each)")
    p.add_argument("--out", type=Path, required=True, help="CSV of the cells (resumable: cells in it are kept)")
    p.add_argument("--md", type=Path, help="also write the table as markdown here")
    p.add_argument("--no-references", action="store_true", help="without the two non-evading references "
                   "(straight at 1 m/s and at full throttle), which otherwise run the same cells")
    p.set_defaults(stage="robust-select")


def _perturbations(spec: str) -> list[str]:
    sep = ";" if ";" in spec else ","
    return ["nominal"] + [s.strip() for s in spec.split(sep) if s.strip()]


def _cell(model: str, path: str | None, perturbation: str, scenario: str, trials: int) -> dict:
    """One `racecav eval` of a model (a policy file, or None: the reference ``model``) on a scenario
    under a perturbation (selection seeds)."""
    from racecav.common.procs import racecav_cmd

    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "run.json"
        ctrl = ["--controller", "drl-avoid", "--model", path] if path else ["--controller", REFERENCES[model]]
        cmd = ["eval", "--scenario", scenario, *ctrl, "--trials", str(trials), "--seed", str(SELECT_SEED), "--mode", "lockstep",
               "--out-dir", tmp, "--json", str(out), "--no-progress"]
        if perturbation != "nominal":
            cmd += ["--perturb", perturbation]
        r = subprocess.run(racecav_cmd(*cmd), capture_output=True, text=True)
        if r.returncode != 0:
            raise RuntimeError(f"{model} {scenario} {perturbation}: racecav eval exited {r.returncode}\n"
                               f"{r.stdout[-2000:]}{r.stderr[-2000:]}")
        s = json.loads(out.read_text())["summary"]
    return {"model": model, "perturbation": perturbation, "scenario": scenario,
            "successes": s["successes"], "trials": s["trials"]}


def run(args, cfg) -> int:
    from tqdm import tqdm

    models = dict(m.split("=", 1) for m in args.models.split(",") if m.strip())
    for name, path in models.items():
        if not Path(path).is_file():
            print(f"racecav train robust-select: {name}: no policy file {path}")
            return 2
    try:
        perts = _perturbations(args.perturbations)
        from racecav.common.perturb import make

        for p in perts[1:]:
            make(p)  # a bad preset or key is an error naming it, before any trial runs
    except ValueError as e:  # pydantic's ValidationError too: its first error's message
        msg = e.errors()[0]["msg"] if hasattr(e, "errors") else str(e)
        print(f"racecav train robust-select: {msg}")
        return 2
    if not args.no_references:
        models.update({name: None for name in REFERENCES})
    todo = [(m, p, s) for m in models for p in perts for s in CONFLICT]
    todo += [(m, "nominal", s) for m in models for s in PAPER]
    rows = []
    if args.out.is_file():
        with args.out.open() as f:
            rows = [r for r in csv.DictReader(f) if int(r["trials"]) == args.trials]
    have = {(r["model"], r["perturbation"], r["scenario"]) for r in rows}
    todo = [c for c in todo if c not in have]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    with ThreadPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        futs = [pool.submit(_cell, m, models[m], p, s, args.trials) for m, p, s in todo]
        for fut in tqdm(futs, desc="robust-select", unit="cell"):
            rows.append(fut.result())
            with args.out.open("w", newline="") as f:  # after every cell: an interrupted run resumes
                w = csv.DictWriter(f, fieldnames=FIELDS, extrasaction="ignore")
                w.writeheader()
                w.writerows(rows)
    text = table(rows, list(models), perts, args)
    print(text)
    if args.md:
        args.md.write_text(text + "\n")
    return 0


def table(rows: list[dict], models: list[str], perts: list[str], args) -> str:
    """Pooled conflict-timed success (%, 95 % Wilson interval) per model and perturbation, and the
    paper-timed cells in the ideal world."""
    from racecav.evaluation.results import wilson

    def pooled(m, p, scens):
        k = sum(int(r["successes"]) for r in rows if r["model"] == m and r["perturbation"] == p and r["scenario"] in scens)
        n = sum(int(r["trials"]) for r in rows if r["model"] == m and r["perturbation"] == p and r["scenario"] in scens)
        if not n:
            return "-"
        lo, hi = wilson(k, n)
        return f"**{100 * k / n:.0f}** [{100 * lo:.0f}, {100 * hi:.0f}]"

    head = ["model"] + [f"conflict-timed, {p}" for p in perts] + [f"paper-timed {s}" for s in PAPER]
    lines = [f"Written by `racecav train robust-select --models {args.models} --perturbations "
             f"'{args.perturbations}' --trials {args.trials}` "
             f"(selection seeds {SELECT_SEED}+; {args.trials} trials per scenario, the conflict-timed "
             "columns pooled over the three scenarios).", "",
             "| " + " | ".join(head) + " |", "|---" + "|---:" * (len(head) - 1) + "|"]
    for m in models:
        cells = [pooled(m, p, CONFLICT) for p in perts] + [pooled(m, "nominal", (s,)) for s in PAPER]
        lines.append(f"| {m} | " + " | ".join(cells) + " |")
    return "\n".join(lines)
