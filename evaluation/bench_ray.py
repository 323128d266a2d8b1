"""``racecav bench ray``: what ``racecav eval --table --ray`` costs against the local pool on this
machine, and the wall time of the full table on N machines projected from measured cell times.

1. The same small table (``--controllers``, ``--sections``, ``--trials``) three times, each in a
   fresh folder and store: the local pool (``--jobs 2``), a local Ray with the default 2 CPUs per
   cell (one cell at a time on 2 cores), and a local Ray with 1 CPU per cell (two at a time, as
   the pool). Wall times, the Ray overhead, and the per-cell times each Ray run logged (its
   services starting, its trials).
2. The projection: the full table as docs/results.md's command makes it (every cell of the
   committed store, docs/results-data, split into Ray cells as ``--ray`` splits them), each cell's
   time = its trials' wall time as stored + the median service start measured in 1. N machines of
   2 cores run N cells at once (2 CPUs each); cells go to the first free machine in submission
   order (Ray's own order for equal tasks); plus the Ray start measured in 1.
"""

from __future__ import annotations

import argparse
import csv
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--controllers", default="scripted,full-throttle", help="the small table's rows")
    p.add_argument("--sections", default="conflict", help="the small table's sections")
    p.add_argument("--trials", type=int, default=4, help="trials per scenario cell of the small table")
    p.add_argument("--machines", default="1,2,4,8,16,32", help="N of the projection")
    p.add_argument("--doc", type=Path, default=Path("docs/results.md"),
                   help="the full table's document: its command and its store (results-data/ beside it)")


def _eval(args, out: Path, *extra: str) -> tuple[float, str]:
    from racecav.common import procs

    cmd = procs.racecav_cmd("eval", "--table", "--controllers", args.controllers, "--sections", args.sections,
                            "--trials", str(args.trials), "--out-dir", str(out), "--doc", str(out / "results.md"),
                            "--store", str(out / "store"), "--no-progress", *extra)
    t0 = time.monotonic()
    r = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.monotonic() - t0
    if r.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd[2:])} exited with {r.returncode}:\n{r.stdout[-2000:]}\n{r.stderr[-2000:]}")
    return wall, r.stdout


def _cells_log(out: Path) -> list[dict]:
    with (out / "table" / "logs" / "ray-cells.csv").open() as f:
        return list(csv.DictReader(f))


def full_table_cells(doc: Path) -> tuple[list[float], str]:
    """(the trials' wall time of each Ray cell of the full table, its command) from the store."""
    import gzip
    import json

    cmd = re.search(r"Written by `(racecav eval --table[^`]*)`", doc.read_text()).group(1)
    k = int(m.group(1)) if (m := re.search(r"--trials-per-scenario (\d+)", cmd)) else 5
    trials = int(m.group(1)) if (m := re.search(r"--trials (\d+)", cmd)) else 100
    chunk = max(1, trials // k)
    cells = []
    for path in sorted((doc.parent / "results-data").glob("*.json.gz")):
        with gzip.open(path, "rt") as f:
            stored = json.load(f)
        walls = [sum(t["wall_s"] for t in c["trials"]) for _, c in sorted(stored.items())]
        if ".scenarios." in path.name:
            cells += walls
        else:  # a suite's files, in chunks of about --trials trials as ray_cells.table_tasks makes them
            cells += [sum(walls[i:i + chunk]) for i in range(0, len(walls), chunk)]
    return cells, cmd


def makespan(cells: list[float], n: int) -> float:
    """Wall time of ``cells`` on ``n`` slots, each cell to the first free slot in order."""
    slots = [0.0] * n
    for c in cells:
        i = slots.index(min(slots))
        slots[i] += c
    return max(slots)


def run(args, cfg) -> int:
    from racecav.common.bench import table, write_section

    import os

    runs = {}
    load0 = os.getloadavg()[0]
    with tempfile.TemporaryDirectory(prefix="racecav-bench-ray-") as tmp:
        tmp = Path(tmp)
        for name, extra in (("local pool (--jobs 2)", ("--jobs", "2")),
                            ("Ray, 2 CPUs per cell (--ray)", ("--ray",)),
                            ("Ray, 1 CPU per cell (--ray --ray-cpus 1)", ("--ray", "--ray-cpus", "1"))):
            out = tmp / str(len(runs))
            print(f"bench ray: {name} ...", flush=True)
            wall, stdout = _eval(args, out, *extra)
            cells = _cells_log(out) if "--ray" in extra else []
            m = re.search(r"cells in ([\d.]+) s wall", stdout)
            runs[name] = {"wall": wall, "cells": cells, "in_cells": float(m.group(1)) if m else None}
            print(f"  {wall:.1f} s", flush=True)
    pool = runs["local pool (--jobs 2)"]["wall"]
    n_cells = len(next(r["cells"] for r in runs.values() if r["cells"]))
    rows = []
    for name, r in runs.items():
        starts = [float(c["start_s"]) for c in r["cells"] if c["start_s"]]
        walls = [float(c["wall_s"]) for c in r["cells"]]
        rows.append([name, f"{r['wall']:.1f}", f"{r['wall'] / pool:.2f}",
                     "-" if r["in_cells"] is None else f"{r['wall'] - r['in_cells']:.1f}",
                     f"{statistics.median(starts):.1f}" if starts else "-",
                     f"{statistics.median(walls):.1f}" if walls else "-"])
    load1 = os.getloadavg()[0]
    cells, cmd = full_table_cells(args.doc)
    proj: dict[int, list] = {int(x): [int(x)] for x in args.machines.split(",")}
    for name, per_machine in (("Ray, 2 CPUs per cell (--ray)", 1), ("Ray, 1 CPU per cell (--ray --ray-cpus 1)", 2)):
        r = runs[name]
        start = statistics.median(float(c["start_s"]) for c in r["cells"] if c["start_s"])
        ray_start = r["wall"] - r["in_cells"]
        per_cell = [c + start for c in cells]
        for n, row in proj.items():
            row += [f"{(makespan(per_cell, n * per_machine) + ray_start) / 3600:.2f}",
                    f"{(sum(per_cell) / (n * per_machine) + ray_start) / 3600:.2f}"]
    starts = {name: statistics.median(float(c["start_s"]) for c in r["cells"] if c["start_s"])
              for name, r in runs.items() if r["cells"]}
    md = ("The same small table (controllers " + args.controllers + ", sections " + args.sections +
          f", {args.trials} trials per scenario cell: {n_cells} Ray cells) three ways, each in a fresh "
          "folder and store, one run each. Overhead = wall time beside the local pool's; Ray start = "
          "wall time outside the cells (starting and stopping the local Ray, writing the document); "
          "cell start = a cell's router, sim and controller starting on its worker.\n\n"
          + table(rows, ["run", "wall (s)", "x local pool", "Ray start + doc (s)", "cell start median (s)",
                         "cell wall median (s)"])
          + f"\n\nLoad average (1 min) {load0:.1f} before, {load1:.1f} after, on 2 cores (other work on the "
          "machine): the absolute times are this load's, the ratios of one run are what compares. On one "
          "2-core machine Ray only adds its start and a service start per cell (the pool starts services "
          "once per row); what it buys is the same command on more machines. In lockstep a cell's sim and "
          "controller take turns, so a cell keeps about one core busy: two cells per 2-core machine "
          "(`--ray-cpus 1`) finish sooner than one (the default 2 CPUs, safe for realtime runs).\n\n"
          f"### The full table on N machines (projected)\n\n`{cmd}`: {len(cells)} Ray cells (a scenario "
          f"cell each, the suites' files in chunks of about --trials trials), {sum(cells) / 3600:.2f} h of "
          "trials as the committed store (docs/results-data) recorded them (measured two rows at a time on "
          "2 cores, `--jobs 2`), plus each run's median cell start and its Ray start measured above "
          f"({', '.join(f'{v:.1f} s' for v in starts.values())} per cell). Machines of 2 cores; cells go to "
          "the first free slot in submission order; even spread: the work divided evenly, the lower bound.\n\n"
          + table(list(proj.values()), ["machines", "--ray: projected wall (h)", "--ray: even spread (h)",
                                        "--ray-cpus 1: projected wall (h)", "--ray-cpus 1: even spread (h)"])
          + f"\n\nThe longest cell's trials take {max(cells) / 60:.1f} min: no number of machines finishes "
          "sooner than that.")
    print(md)
    if not args.no_doc:
        argv = " ".join(sys.argv[sys.argv.index("bench"):]) if "bench" in sys.argv else "bench ray"
        print(f"wrote {write_section('ray', 'racecav ' + argv, md)}")
    return 0
