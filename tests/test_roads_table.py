"""The table's generalization section (``--sections roads``) on a small hand-made suite with the
roads suite's splits (test, ood, controls): split names and families come from its manifest, the
cells go to the store and the document is rewritten from it alone; no suite: skipped, named."""

import json
import shutil
import subprocess
from pathlib import Path

from racecav.common import procs
from racecav.common.scenario import SCENARIOS_DIR

PARKED = """
name = "{name}"
world = "intersection"
duration_s = 7.0
[ego]
x = -4.0
y = 0.0
yaw_deg = 0.0
speed = 1.0
[[obstacles]]
x = 0.0
y = 0.8
yaw_deg = 0.0
speed = 0.0
[success]
min_progress_m = 4.0
"""


def _suite(root: Path) -> Path:
    """test: one conflict (crossing); ood: one head-on; controls: a car parked beside the road."""
    entries = {"train": [], "test": [], "ood": [], "controls": []}
    for split, family, src in (("test", "crossing", "conflict-right-to-left"), ("ood", "head-on", "conflict-head-to-head"),
                               ("controls", "parked-beside", None)):
        (root / split).mkdir(parents=True)
        f = root / split / f"{family}-000.toml"
        if src is None:
            f.write_text(PARKED.format(name=f"{family}-000"))
        else:
            shutil.copy(SCENARIOS_DIR / f"{src}.toml", f)
        entries[split].append({"file": f"{split}/{f.name}", "family": family})
    (root / "suite.json").write_text(json.dumps({"name": "mini", "families": ["crossing", "head-on", "parked-beside"],
                                                 "splits": entries}))
    return root


def _eval(out: Path, *args, timeout=300):
    return subprocess.run(procs.racecav_cmd("eval", "--table", "--sections", "roads", *args, "--out-dir", str(out),
                                            "--no-progress"), capture_output=True, text=True, timeout=timeout)


def test_roads_section_from_the_manifest_and_the_store(tmp_path):
    suite = _suite(tmp_path / "mini")
    doc, store = tmp_path / "docs" / "results.md", tmp_path / "docs" / "results-data"
    args = ("--roads-suite", str(suite), "--controllers", "scripted,full-throttle", "--trials-per-scenario", "1",
            "--doc", str(doc))
    r = _eval(tmp_path / "out", *args)
    assert r.returncode == 0, r.stdout + r.stderr
    text = doc.read_text()
    assert "## Generalization: the `mini` suite" in text and "(tmp_path)" not in text
    assert "| in-distribution test success | OOD test success | controls success |" in text
    for title, fam in (("in-distribution test", "crossing"), ("OOD test", "head-on"), ("controls", "parked-beside")):
        assert f"### `mini`, {title} split, per family" in text and f"| controller | {fam} |" in text
    section = text[text.index("## Generalization"):]
    rows = [line for line in section.splitlines() if line.startswith("| no evasion")]
    # the references: crash into both conflicts, pass the control
    row = rows[0].split("|")
    assert row[2].strip().startswith("**0**") and row[3].strip().startswith("**0**") and row[4].strip().startswith("**100**")
    assert (doc.parent / "img" / "results-mini.png").is_file()
    for split in ("test", "ood", "controls"):
        assert (store / f"scripted.suite-mini-{split}.json.gz").is_file()
    res = json.loads((tmp_path / "out" / "table" / "suite-mini-test" / "scripted.json").read_text())
    assert res["summary"]["measured"] == 1 and res["summary"]["impact_bands"] is not None
    # from the store alone: the same tables, no trial run
    again = tmp_path / "again.md"
    r = _eval(tmp_path / "out2", *args[:-1], str(again), "--from-store", "--store", str(store))
    assert r.returncode == 0, r.stdout + r.stderr
    strip = lambda t: [line for line in t.splitlines() if line.startswith("|")]  # noqa: E731
    assert strip(again.read_text()) == strip(text) and not list((tmp_path / "out2").rglob("*.jsonl"))
    # its rows picked: only full-throttle has a roads row
    r = _eval(tmp_path / "out2", *args[:-1], str(again), "--from-store", "--store", str(store),
              "--roads-controllers", "full-throttle")
    assert r.returncode == 0, r.stdout + r.stderr
    section = again.read_text()[again.read_text().index("## Generalization"):]
    assert sum(line.startswith("| no evasion") for line in section.splitlines()) == 1 + 3 + 3  # splits, impacts, families
    r = _eval(tmp_path / "out2", *args, "--roads-controllers", "mpc-apf")
    assert r.returncode == 2 and "--roads-controllers" in r.stderr


def test_roads_section_skipped_when_the_suite_is_not_generated(tmp_path):
    r = _eval(tmp_path / "out", "--roads-suite", str(tmp_path / "none"), "--controllers", "scripted",
              "--doc", str(tmp_path / "results.md"), "--from-store", "--store", str(tmp_path / "store"), timeout=120)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "section roads skipped" in r.stderr and "racecav suite generate" in r.stderr
    assert "Generalization" not in (tmp_path / "results.md").read_text()
