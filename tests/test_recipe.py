"""`racecav train recipe`: the committed avoid recipe starts from committed weights named by
their digest; a recipe's stages run in chunks, resume, chain (stage 2 from stage 1's final
checkpoint, also from the committed record on a fresh root), and a recipe, a start or a run
folder that does not fit is refused in one line (tiny real PPO runs on the fast world)."""

from __future__ import annotations

import csv
import hashlib
import json
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
START = "common/data/policies/reversed.zip"


def _sha(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def test_avoid_recipe_starts_from_committed_weights_named_by_digest():
    from racecav.training.recipe import load_recipe, resolve

    path = resolve("avoid")
    assert path == ROOT / "training" / "recipes" / "avoid.toml"
    recipe = load_recipe(path, configs=False)
    first = recipe.stages[0]
    assert first.after is None and (ROOT / first.start).is_file()
    assert _sha(ROOT / first.start) == first.start_sha256
    assert [s.after for s in recipe.stages[1:]] == [s.name for s in recipe.stages[:-1]]  # a chain
    assert all(s.what.strip() and s.steps > 0 for s in recipe.stages)
    # every stage's settings are a valid TrainConfig, a run of which can start (training/train.config_problem)
    assert [s.train_config().expert for s in load_recipe(path).stages] == ["predictive"] * len(recipe.stages)


def _stage(name: str, start: str, steps: int, lr: float = 3e-4, sha: str | None = None) -> str:
    digest = f'start_sha256 = "{sha}"\n' if sha else ""
    return f"""
[[stages]]
name = "{name}"
what = "a few PPO updates"
command = "overtake"
steps = {steps}
start = "{start}"
{digest}
[stages.config]
preset = "fast"
seed = 3
n_steps = 16
batch_size = 32
n_epochs = 1
learning_rate = {lr}
normalize = true
checkpoint_every = 64

[stages.config.env]
heading = "reversed"
n_obstacles = 2
n_envs = 4
"""


def _recipe(tmp_path: Path, first: str = "", lr: float = 3e-4, sha: str | None = None, extra: str = "") -> Path:
    path = tmp_path / "tiny.toml"
    path.write_text('name = "tiny"\ndescription = "two tiny PPO stages"\n' + extra
                    + (first or _stage("first", START, 192, lr, sha or _sha(ROOT / START)))
                    + _stage("second", "stage:first", 128))
    return path


def _run(capsys, *args) -> tuple[int, str]:
    from racecav.cli import main

    capsys.readouterr()
    rc = main(["train", "recipe", *map(str, args), "--no-progress"])
    return rc, capsys.readouterr().out


def _timesteps(run: Path) -> list[int]:
    with (run / "progress.csv").open() as f:
        return [int(float(r["timesteps"])) for r in csv.DictReader(f)]


def test_recipe_runs_in_chunks_resumes_and_chains(tmp_path, capsys, monkeypatch):
    from racecav.cli import main
    from racecav.training.recipe import config_sha256, load_recipe

    recipe, root = _recipe(tmp_path), tmp_path / "runs"
    folder = root / "tiny"
    # a chunk: stage 1 stops part-way, after a checkpoint; stage 2 has not begun
    assert _run(capsys, recipe, "--root", root, "--chunk-steps", 64)[0] == 0
    assert json.loads((folder / "first" / "latest.json").read_text())["timesteps"] == 64
    assert _timesteps(folder / "first") == [64] and not (folder / "second").exists()
    m = json.loads((folder / "manifest.json").read_text())
    assert m["recipe"] == "tiny" and m["sha256"] == _sha(recipe)
    first = m["stages"][0]
    assert (first["samples"], first["steps"], first["done"]) == (64, 192, False)
    assert first["start_path"] == START and first["start_sha256"] == _sha(ROOT / START)
    assert "end_sha256" not in first and m["stages"][1]["samples"] == 0

    # the next invocation resumes stage 1 to its end (one learning curve), then runs stage 2 from
    # stage 1's final checkpoint
    assert _run(capsys, recipe, "--root", root)[0] == 0
    assert _timesteps(folder / "first") == [64, 128, 192]
    assert json.loads((folder / "second" / "latest.json").read_text())["timesteps"] == 128
    m = json.loads((folder / "manifest.json").read_text())
    first, second = m["stages"]
    end = folder / "first" / "checkpoints" / first["end_checkpoint"]
    assert first["done"] and first["end_checkpoint"] == "step_000000192.zip" and first["end_sha256"] == _sha(end)
    assert second["start"] == "stage:first" and second["start_sha256"] == first["end_sha256"]
    assert json.loads((folder / "second" / "config.json").read_text())["init_from"] == str(end)
    stages = load_recipe(recipe).stages
    assert [e["config_sha256"] for e in m["stages"]] == [config_sha256(s.train_config()) for s in stages]
    assert second["done"] and first["wall_s"] > 0
    # done: nothing more to run
    assert _run(capsys, recipe, "--root", root)[0] == 0
    assert _timesteps(folder / "second") == [64, 128]

    # the record: a fresh root starts stage 2 from stage 1's recorded weights, checked by digest
    assert _run(capsys, recipe, "--root", root, "--record")[0] == 0
    rec = tmp_path / "tiny"
    assert json.loads((rec / "first" / "config.json").read_text())["init_from"] == START
    assert _sha(rec / "first" / "step_000000192.zip") == first["end_sha256"]
    assert (rec / "first" / "step_000000192.vecnorm.pkl").is_file() and (rec / "second" / "progress.csv").is_file()
    fresh = tmp_path / "fresh"
    assert _run(capsys, recipe, "--root", fresh, "--stage", "second", "--chunk-steps", 64)[0] == 0
    m2 = json.loads((fresh / "tiny" / "manifest.json").read_text())
    assert m2["stages"][0]["from"] == "record" and m2["stages"][1]["start_sha256"] == first["end_sha256"]
    assert m2["stages"][1]["start_path"] == str(rec / "first" / "step_000000192.zip")
    (rec / "first" / "step_000000192.zip").write_bytes(b"not the weights")  # a changed record is refused
    rc, out = _run(capsys, recipe, "--root", tmp_path / "fresh2", "--stage", "second")
    assert rc == 2 and len(out.strip().splitlines()) == 1
    assert f"expected sha256 {first['end_sha256']}, got {hashlib.sha256(b'not the weights').hexdigest()}" in out

    # ship --recipe: the policy's metadata names the recipe, its digest and the stage (shipped into
    # tmp_path: the run's record goes there too, not into the repository)
    import racecav.common.policy as policy_mod
    import racecav.training.runs as runs_mod

    monkeypatch.setattr(policy_mod, "MODELS_DIR", tmp_path / "policies")
    monkeypatch.setattr(runs_mod, "COMMITTED", tmp_path / "records")
    ship = ["train", "ship", "--run-dir", str(folder / "second"), "--checkpoint", "latest", "--name", "tiny"]
    assert main([*ship, "--recipe", str(recipe)]) == 0
    meta = json.loads((tmp_path / "policies" / "tiny.json").read_text())
    assert meta["recipe"] == {"name": "tiny", "file": str(recipe), "sha256": _sha(recipe), "stage": "second"}

    # a changed setting of a started (here: finished) stage: refused, naming the key
    recipe = _recipe(tmp_path, lr=1e-4)
    rc, out = _run(capsys, recipe, "--root", root)
    assert rc == 2 and len(out.strip().splitlines()) == 1
    assert "first/config.json: differs from stage 'first' of the recipe in learning_rate " in out
    # nor does ship name a recipe whose settings the run does not have
    capsys.readouterr()
    ship[3] = str(folder / "first")
    assert main([*ship, "--recipe", str(recipe)]) == 2
    assert "differs from stage 'first' of the recipe in learning_rate " in capsys.readouterr().out


def test_bad_recipes_are_refused_in_one_line(tmp_path, capsys):
    wrong = "0" * 64
    rc, out = _run(capsys, _recipe(tmp_path, sha=wrong), "--root", tmp_path / "runs")
    assert rc == 2 and len(out.strip().splitlines()) == 1
    assert f"start {START}: expected sha256 {wrong}, got {_sha(ROOT / START)}" in out
    assert not (tmp_path / "runs" / "tiny" / "first").exists()
    missing = _stage("first", "common/data/policies/nothing.zip", 64, sha=wrong)
    rc, out = _run(capsys, _recipe(tmp_path, first=missing), "--root", tmp_path / "runs")
    assert rc == 2 and "start common/data/policies/nothing.zip: expected sha256 " + wrong + ", got no such file" in out
    for broken, field in ((_stage("first", START, 64, sha=wrong).replace("steps =", "stepz ="), "stages.0.stepz"),
                          (_stage("first", START, 64, sha=wrong).replace("n_envs", "n_env"), "config.env.n_env"),
                          (_stage("first", START, 64, sha=wrong).replace("seed = 3", "seed = 3\ninit_from = 'x.zip'"),
                           "config.init_from")):
        rc, out = _run(capsys, _recipe(tmp_path, first=broken), "--root", tmp_path / "runs")
        assert rc == 2 and len(out.strip().splitlines()) == 1 and field in out, out
    rc, out = _run(capsys, _recipe(tmp_path, extra='stagez = 1\n'), "--root", tmp_path / "runs")
    assert rc == 2 and "stagez: unknown field" in out
    # training data that is not there (a suite not generated on this clone): refused before a run folder
    nosuite = _stage("first", START, 64, sha=_sha(ROOT / START)).replace(
        "n_envs = 4", 'n_envs = 4\nscenarios = "no-such-suite"\nscenario_share = 0.5')
    rc, out = _run(capsys, _recipe(tmp_path, first=nosuite), "--root", tmp_path / "runs")
    assert rc == 2 and len(out.strip().splitlines()) == 1
    assert "env.scenarios: suite no-such-suite" in out and "racecav suite generate --name no-such-suite" in out
    assert not (tmp_path / "runs" / "tiny" / "first").exists()


def test_each_avoid_stage_runs_a_short_chunk_and_resumes(tmp_path, capsys):
    """The committed avoid recipe's stages, as they are but small (4 worlds of 8 steps, a few
    hundred samples) and on a small generated roads sample instead of the suites: each stage
    starts (the first from the committed start, checked by digest), stops after a chunk, resumes
    and chains (the predictive teacher, the map redraws and DAgger's fit on every stage)."""
    import tomli_w

    from racecav.evaluation.benchmark import generate, load_benchmark
    from racecav.training.recipe import load_recipe, resolve

    bf = load_benchmark("roads")
    bf = bf.model_copy(update={"families": [f for f in bf.families if f.name in ("crossing", "from-rest", "braking")]})
    generate(bf, tmp_path / "roads", seed=0, splits=("train",), progress=False, n_train=1)
    small = {"n_steps": 8, "batch_size": 16, "grad_steps": 2, "dataset_max": 4096, "checkpoint_every": 32,
             "map_resample_every": 1}
    stages = []
    for st in load_recipe(resolve("avoid")).stages:
        cfg = {**st.config, **small, "env": {**st.config["env"], "n_envs": 4, "scenario_maps": 2,
                                            "scenarios": str(tmp_path / "roads")}}
        stages.append({**st.model_dump(exclude_none=True), "steps": 64, "config": cfg})
    path = tmp_path / "small.toml"
    path.write_text(tomli_w.dumps({"name": "small", "description": "the avoid recipe, small", "stages": stages}))
    folder = tmp_path / "runs" / "small"
    names = [s["name"] for s in stages]
    for i, name in enumerate(names):
        assert _run(capsys, path, "--root", tmp_path / "runs", "--chunk-steps", 32)[0] == 0
        assert _timesteps(folder / name) == [32]  # stopped part-way
        assert _run(capsys, path, "--root", tmp_path / "runs", "--chunk-steps", 32)[0] == 0
        assert _timesteps(folder / name) == [32, 64]  # resumed to its end
        m = json.loads((folder / "manifest.json").read_text())
        assert m["stages"][i]["done"]
        if i:
            assert m["stages"][i]["start_sha256"] == m["stages"][i - 1]["end_sha256"]
        else:
            assert m["stages"][0]["start_sha256"] == _sha(ROOT / START)
