"""docs/results.md's generalization section: the roads suite's splits (in-distribution test, OOD
test, controls) per controller, per family, with the benchmark's measures (results.Measures)."""

from __future__ import annotations

from pathlib import Path

SPLIT_TITLES = {"test": "in-distribution test", "ood": "OOD test", "controls": "controls"}
"""Column titles of the manifest's split names (any other split is titled by its name)."""


def _title(split: str) -> str:
    return SPLIT_TITLES.get(split, split)


def _rate(sm: dict) -> str:
    if not sm["trials"]:
        return "not run"
    lo, hi = sm["ci95"]
    return f"**{100 * sm['success_rate']:.0f}** [{100 * lo:.0f}, {100 * hi:.0f}]"


def _share(k: int | None, n: int | None) -> str:
    return "n/a" if not n or k is None else f"{100 * k / n:.0f}"


def _f(v: float | None, d: int = 2) -> str:
    return "n/a" if v is None else f"{v:.{d}f}"


def roads_section(roads: dict, docs: dict, img: Path, doc: Path, label=str) -> list[str]:
    """Markdown lines of the section.

    :param roads: split -> (suite name, cells) as the table ran them (the manifest's splits but train).
    :param docs: split -> {row key: suite_eval.suite_json of that row on the split}.
    :param label: a row key's label in the tables.
    """
    from racecav.evaluation.metrics import IMPACT_BANDS_MPS
    from racecav.evaluation.plots import plot_success_bars

    splits = [sp for sp in roads if docs.get(sp)]
    if not splits:
        return []
    rows = list(dict.fromkeys(n for sp in splits for n in docs[sp]))
    name = next(iter(roads.values()))[0]
    one = next(iter(docs[splits[0]].values()))
    k, seed = one["trials_per_scenario"], one["base_seed"]
    sizes = ", ".join(f"{_title(sp)} {len(roads[sp][1])} files" for sp in splits)
    bands = " / ".join(f"{b:.2f}" for b in IMPACT_BANDS_MPS)
    lines = [f"## Generalization: the `{name}` suite (roads it never trained on)", "",
             f"`racecav suite generate --name {name}` (common/data/suites/{name}.toml, docs/world.md): procedural "
             "worlds and behaviours, split at the level of maps. In-distribution test: disjoint seeds of the "
             "train split's ranges; OOD test: only the bands the train split never draws; controls: the same "
             f"generator with nothing to avoid (a car that stops short, turns away, passes well ahead or behind, "
             f"starts from rest ...). {sizes}, {k} trials each (trial i: seed {seed} + i), the same seeds for every "
             "controller, through the services like every cell here. Success rates with 95 % Wilson intervals; the "
             "two references (no evasion at 1 m/s, at full throttle) on the same seeds must be near 0 on the "
             "conflicts and near 100 on the controls.", "",
             "Per-trial measures (evaluation/metrics.py, recorded in each trial's `measures`): **frozen**: "
             "standing (< 0.05 m/s) more than 2 s while its path was free (no other car in the corridor 1.5 m "
             "ahead of its bumper, its width + 0.1 m either side, then or in the next 1 s), or the time ran out "
             "without contact short of its route; **driving score**: the CARLA Leaderboard's, route completion "
             "(progress / the file's min_progress_m) x 0.6 for a collision with a car, 0.65 with a wall, 0.7 for "
             "a timeout, averaged over trials; **impact speed**: relative to what was hit, at the last control "
             f"step before contact, in the Euro NCAP AEB bands Froude-scaled to 1/10 (below {bands} m/s score "
             "1 / 0.75 / 0.5 / 0.25, above 0); **drive-off**: from rest, the time its speed first reaches 0.2 m/s.",
             "", "| controller | " + " | ".join(f"{_title(sp)} success" for sp in splits)
             + " | frozen % (" + " / ".join(_title(sp) for sp in splits) + ") | collisions ("
             + " / ".join(_title(sp) for sp in splits) + ") | driving score ("
             + " / ".join(_title(sp) for sp in splits) + ") |",
             "|---|" + "---:|" * (len(splits) + 3)]
    chart = []
    for n in rows:
        sms = [docs[sp].get(n, {}).get("summary") for sp in splits]
        cells = [_rate(sm) if sm else "not run" for sm in sms]
        frozen = " / ".join(_share(sm.get("frozen"), sm.get("measured")) if sm else "n/a" for sm in sms)
        coll = " / ".join(str(sm["collisions"]) if sm else "n/a" for sm in sms)
        score = " / ".join(_f(sm.get("mean_driving_score")) if sm else "n/a" for sm in sms)
        lines.append(f"| {label(n)} | " + " | ".join(cells) + f" | {frozen} | {coll} | {score} |")
        chart.append((label(n), [(sm["success_rate"], tuple(sm["ci95"]) if sm["ci95"] else None, None)
                                  if sm and sm["trials"] else (None, None, None) for sm in sms]))
    path = plot_success_bars(chart, [_title(sp) for sp in splits], img / f"results-{name}.png",
                             title=f"Suite {name}: success per split, {k} trials per file (95 % CI)")
    lines += ["", f"![{name}]({path.relative_to(doc.parent)})", ""]
    # impacts and drive-off, per controller and split
    edges = [f"< {b:.2f}" for b in IMPACT_BANDS_MPS] + [f">= {IMPACT_BANDS_MPS[-1]:.2f}"]
    lines += ["| controller | split | collisions | median impact (m/s) | collisions per Euro NCAP band ("
              + " / ".join(edges) + " m/s) | from rest | never drove off | median drive-off (s) |",
              "|---|---|---:|---:|---:|---:|---:|---:|"]
    for n in rows:
        for sp in splits:
            sm = docs[sp].get(n, {}).get("summary")
            if not sm or not sm.get("measured"):
                continue
            lines.append(f"| {label(n)} | {_title(sp)} | {sm['collisions']} | {_f(sm['median_impact_speed_mps'])} "
                         f"| {' / '.join(str(b) for b in sm['impact_bands'])} | {sm['from_rest']} | "
                         f"{sm['never_drove_off']} | {_f(sm['median_drive_off_s'])} |")
    lines.append("")
    # per family, one table per split: success [CI] (frozen %)
    for sp in splits:
        fams = list(dict.fromkeys(c.family for c in roads[sp][1]))
        lines += [f"### `{name}`, {_title(sp)} split, per family", "",
                  "Success % [95 % CI] (frozen %).", "",
                  "| controller | " + " | ".join(fams) + " |", "|---|" + "---:|" * len(fams)]
        for n in rows:
            fd = docs[sp].get(n, {}).get("families", {})
            cells = []
            for fam in fams:
                sm = fd.get(fam)
                cells.append("not run" if not sm or not sm["trials"] else
                             f"{_rate(sm)} ({_share(sm.get('frozen'), sm.get('measured'))})")
            lines.append(f"| {label(n)} | " + " | ".join(cells) + " |")
        lines.append("")
    return lines
