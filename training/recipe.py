"""``racecav train recipe NAME``: a policy rebuilt by its stages from committed weights.

    racecav train recipe NAME_OR_PATH [--stage NAME] [--chunk-steps N] [--root DIR] [--no-progress]
    racecav train recipe NAME_OR_PATH --record [DIR]

A recipe is a data file (training/recipes/NAME.toml, schema :class:`Recipe`): a name, a
description and ``[[stages]]``, each a training run of ``racecav train racing|overtake|dagger``
with its full TrainConfig (common/config.py) and its start: a committed SB3 zip named by its
sha256, or ``stage:<earlier stage>`` (that stage's final checkpoint). The runner sets
``init_from`` from the start; the recipe does not.

Each stage runs in ROOT/NAME/STAGE (default runs/recipes), a run folder as training/train.py
writes it, so a stopped stage resumes (``--resume``) after its config.json was checked against
the recipe. ``--chunk-steps N`` stops after N more samples (a checkpoint first): a long recipe
runs in chunks across sessions. ROOT/NAME/manifest.json is rewritten after every chunk (the
recipe's digest; per stage its start and digest, the config's digest, the digest of its
scenario files (a generated suite is made again on a fresh clone), samples, wall time, the final
checkpoint's digest). ``--record`` copies what a fresh clone needs into
training/recipes/NAME/ (committed): the manifest, each stage's config.json and progress.csv, each
finished stage's final checkpoint; a ``stage:X`` start is taken from there when ROOT has no
finished X, checked against the digest the manifest recorded.
"""

from __future__ import annotations

import hashlib
import json
import logging
import shutil
import time
import tomllib
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from racecav.training.runs import REPO, load_run_config

log = logging.getLogger("racecav.train")

RECIPES = Path(__file__).resolve().parent / "recipes"
"""The committed recipes (NAME.toml) and their records (NAME/)."""
ROOT = Path("runs") / "recipes"
"""Where the stages run (ROOT/NAME/STAGE), unless --root."""
STAGE_PREFIX = "stage:"
SETTINGS_IGNORED = ("init_from",)
"""TrainConfig fields that are not the recipe's settings: the runner sets init_from from the start
(its spelling differs between a run folder and a fresh clone; the manifest records its digest)."""


class RecipeError(ValueError):
    """A recipe, a start file or a run folder that does not fit (one line: the CLI exits 2)."""


class Stage(BaseModel):
    """One training run of a recipe."""

    model_config = ConfigDict(extra="forbid", use_attribute_docstrings=True)

    name: str = Field(pattern=r"^[A-Za-z0-9][A-Za-z0-9_-]*$")
    """Its run folder's name (ROOT/NAME/<name>) and how later stages and --stage name it."""
    command: Literal["racing", "overtake", "dagger"]
    """The ``racecav train`` sub-command that runs it (its TrainConfig.stage)."""
    steps: int = Field(ge=1)
    """The sample count at which the stage ends (each stage is a new run: counted from its start)."""
    start: str = Field(min_length=1)
    """A committed SB3 zip (repo-relative path, with start_sha256) or ``stage:<earlier stage>``."""
    start_sha256: str | None = Field(None, pattern=r"^[0-9a-f]{64}$")
    """The sha256 of the start file (required for a file, not for ``stage:``)."""
    what: str = Field(min_length=1)
    """One sentence for the docs: what this stage does."""
    config: dict
    """The stage's full TrainConfig (common/config.py) but init_from (and stage: the command)."""

    @model_validator(mode="after")
    def _check(self):
        if self.start.startswith(STAGE_PREFIX):
            if self.start_sha256 is not None:
                raise ValueError("start_sha256: a stage: start has no fixed digest (the manifest records it)")
        elif self.start_sha256 is None:
            raise ValueError(f"start_sha256: required with start = {self.start!r} (a file)")
        if "init_from" in self.config:
            raise ValueError("config.init_from: set by the runner from start; remove it")
        if self.config.get("stage", self.command) != self.command:
            raise ValueError(f"config.stage: {self.config['stage']!r} differs from command {self.command!r}")
        return self

    @property
    def after(self) -> str | None:
        """The stage this one starts from, if any."""
        return self.start.removeprefix(STAGE_PREFIX) if self.start.startswith(STAGE_PREFIX) else None

    def train_config(self):
        """The stage's TrainConfig (init_from unset). :raises RecipeError: naming the field."""
        from racecav.common.config import TrainConfig

        try:
            return TrainConfig.model_validate({**self.config, "stage": self.command})
        except ValidationError as e:
            raise RecipeError(f"stage {self.name!r}: " + _errors(e, "config.")) from None


class Recipe(BaseModel):
    """A recipe file (training/recipes/NAME.toml)."""

    model_config = ConfigDict(extra="forbid", use_attribute_docstrings=True)

    name: str = Field(pattern=r"^[A-Za-z0-9][A-Za-z0-9_-]*$")
    """Its name: the file's name without .toml."""
    description: str = Field(min_length=1)
    """What the recipe builds."""
    stages: list[Stage] = Field(min_length=1)
    """The runs, in order."""

    @model_validator(mode="after")
    def _check(self):
        seen: list[str] = []
        for i, st in enumerate(self.stages):
            if st.name in seen:
                raise ValueError(f"stages.{i}.name: {st.name!r} twice")
            if st.after is not None and st.after not in seen:
                raise ValueError(f"stages.{i}.start: {st.start!r} is not an earlier stage "
                                 f"({', '.join(seen) or 'none'})")
            seen.append(st.name)
        return self

    def stage(self, name: str) -> Stage:
        for st in self.stages:
            if st.name == name:
                return st
        raise RecipeError(f"--stage {name}: not a stage of {self.name} ({', '.join(s.name for s in self.stages)})")


def _errors(e: ValidationError, prefix: str = "") -> str:
    """pydantic errors as one line: ``field.path: message``."""
    out = []
    for err in e.errors():
        field = prefix + ".".join(str(p) for p in err["loc"])
        msg = err["msg"].removeprefix("Value error, ")
        if err["type"] == "extra_forbidden":
            out.append(f"{field}: unknown field")
        elif err["type"] == "missing":
            out.append(f"{field}: field required")
        elif not err["loc"]:  # a model validator's message names its field itself
            out.append(prefix + msg)
        else:
            out.append(f"{field}: {msg} (got {err.get('input')!r})")
    return "; ".join(out)


def resolve(spec: str | Path) -> Path:
    """The recipe file of a name (training/recipes/NAME.toml) or a path."""
    p = Path(spec)
    if p.suffix == ".toml" or p.is_file():
        return p
    return RECIPES / f"{spec}.toml"


def load_recipe(path: Path, configs: bool = True) -> Recipe:
    """Read and check a recipe file; ``configs``: also each stage's TrainConfig (and what a run
    of it needs). :raises RecipeError: one line naming the file and the field."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise RecipeError(f"{shown(path)}: no such recipe (names: {', '.join(names()) or 'none'})") from None
    except tomllib.TOMLDecodeError as e:
        raise RecipeError(f"{shown(path)}: not TOML ({e})") from None
    try:
        recipe = Recipe.model_validate(data)
    except ValidationError as e:
        raise RecipeError(f"{shown(path)}: {_errors(e)}") from None
    if recipe.name != path.stem:
        raise RecipeError(f"{shown(path)}: name: {recipe.name!r} must be the file's name ({path.stem!r})")
    if configs:
        from racecav.training.train import config_problem

        for st in recipe.stages:
            try:
                tc = st.train_config()
            except RecipeError as e:
                raise RecipeError(f"{shown(path)}: {e}") from None
            # a stage always has a start: check the rest of what a run needs
            problem = config_problem(tc.model_copy(update={"init_from": st.start}))
            if problem:
                raise RecipeError(f"{shown(path)}: stage {st.name!r}: {problem}")
    return recipe


def names() -> list[str]:
    """The committed recipes."""
    return sorted(p.stem for p in RECIPES.glob("*.toml"))


# ----------------------------------------------------------------------------------- digests
def sha256(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def settings(tc) -> dict:
    """A TrainConfig's settings as the recipe states them (JSON types, init_from left out)."""
    return tc.model_dump(mode="json", exclude=set(SETTINGS_IGNORED))


def config_sha256(tc) -> str:
    """The digest of a stage's settings: sha256 of their canonical JSON (sorted keys, no spaces)."""
    text = json.dumps(settings(tc), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()


def scenarios_sha256(tc) -> str | None:
    """The digest of a run's scenario episodes (the train split of ``env.scenarios``: each file's
    family and bytes, in order); None without scenarios. A generated suite (runs/suites/, not
    committed) is made again on a fresh clone: this says whether it is the same.

    :raises RecipeError: a suite that is not there (naming the command that makes it).
    """
    if not tc.env.scenarios:
        return None
    from racecav.common.scenario import scenario_sources

    try:
        sources = scenario_sources(tc.env.scenarios, "train")
    except (ValueError, FileNotFoundError) as e:
        raise RecipeError(f"env.scenarios: {e}") from None
    h = hashlib.sha256()
    for f, family in sources:
        h.update(family.encode() + b"\0" + Path(f).read_bytes() + b"\0")
    return h.hexdigest()


def differing_keys(a: dict, b: dict, prefix: str = "") -> list[str]:
    """The dotted keys whose values differ between two nested dicts."""
    out = []
    for k in sorted(set(a) | set(b)):
        va, vb = a.get(k), b.get(k)
        if isinstance(va, dict) and isinstance(vb, dict):
            out += differing_keys(va, vb, f"{prefix}{k}.")
        elif va != vb:
            out.append(prefix + k)
    return out


def check_run_config(run_dir: Path, stage: Stage) -> None:
    """The run in ``run_dir`` has the recipe's settings for ``stage``.

    :raises RecipeError: naming the keys that differ.
    """
    try:
        tc_run = load_run_config(run_dir)[0]
    except (ValueError, FileNotFoundError) as e:
        raise RecipeError(f"{run_dir / 'config.json'}: {e}") from None
    diff = differing_keys(settings(stage.train_config()), settings(tc_run))
    if diff:
        raise RecipeError(f"{run_dir / 'config.json'}: differs from stage {stage.name!r} of the recipe in "
                          f"{', '.join(diff)} (another run folder, --root, or the recipe's values)")


def shown(path: Path) -> str:
    """A path as the manifest records it: relative to the repository or the working directory."""
    path = Path(path).absolute()
    for base in (REPO, Path.cwd()):
        try:
            return str(path.relative_to(base))
        except ValueError:
            pass
    return str(path)


# ----------------------------------------------------------------------------------- run folders
def _latest(run_dir: Path) -> dict | None:
    p = run_dir / "latest.json"
    return json.loads(p.read_text()) if (run_dir / "latest.zip").is_file() and p.is_file() else None


def _final_checkpoint(run_dir: Path, latest: dict) -> Path:
    """The checkpoint a finished run ended with (latest.zip is its copy)."""
    ck = run_dir / "checkpoints" / f"{latest['checkpoint']}.zip"
    return ck if ck.is_file() else run_dir / "latest.zip"


class Runner:
    """One recipe's stages in ROOT/NAME and its record (training/recipes/NAME/)."""

    def __init__(self, recipe: Recipe, path: Path, root: Path, record_dir: Path | None = None):
        self.recipe, self.path = recipe, Path(path)
        self.folder = Path(root) / recipe.name
        self.record_dir = record_dir or self.path.parent / recipe.name

    def run_dir(self, st: Stage) -> Path:
        return self.folder / st.name

    def recorded(self) -> dict:
        """The record's manifest ({} if none)."""
        p = self.record_dir / "manifest.json"
        return json.loads(p.read_text()) if p.is_file() else {}

    def _recorded_stage(self, st: Stage) -> dict | None:
        for e in self.recorded().get("stages", []):
            if e.get("name") == st.name:
                return e
        return None

    def start_of(self, st: Stage) -> tuple[Path, str]:
        """(file, sha256) a new run of ``st`` starts from, checked.

        :raises RecipeError: one line: the path, the expected and the found digest, or why none.
        """
        if st.after is None:
            p = REPO / st.start
            got = sha256(p) if p.is_file() else "no such file"
            if got != st.start_sha256:
                raise RecipeError(f"stage {st.name!r}: start {st.start}: expected sha256 {st.start_sha256}, got {got}")
            return p, got
        src = self.recipe.stage(st.after)
        run = self.run_dir(src)
        latest = _latest(run)
        if latest is not None and latest["timesteps"] >= src.steps:
            check_run_config(run, src)
            ck = _final_checkpoint(run, latest)
            return ck, sha256(ck)
        entry = self._recorded_stage(src)
        if entry is not None and entry.get("done"):
            if entry.get("config_sha256") != config_sha256(src.train_config()):
                raise RecipeError(f"stage {st.name!r}: start {st.start}: the weights recorded in {self.record_dir} "
                                  f"were trained with other settings (config_sha256 {entry.get('config_sha256')}); "
                                  "run the stage")
            ck = self.record_dir / src.name / entry["end_checkpoint"]
            got = sha256(ck) if ck.is_file() else "no such file"
            if got != entry["end_sha256"]:
                raise RecipeError(f"stage {st.name!r}: start {shown(ck)}: expected sha256 {entry['end_sha256']}, "
                                  f"got {got}")
            return ck, got
        raise RecipeError(f"stage {st.name!r}: starts from stage {src.name!r}, which has not finished "
                          f"(no finished run in {run}, none recorded in {self.record_dir})")

    # ------------------------------------------------------------------------------- manifest
    def manifest(self) -> dict:
        """The manifest, from the run folders (a stage not run here: the record's entry, if any)."""
        from racecav.common.bench import git_commit

        stages = []
        for st in self.recipe.stages:
            run = self.run_dir(st)
            latest = _latest(run)
            if latest is None:
                entry = self._recorded_stage(st)
                stages.append({**entry, "from": "record"} if entry else
                              {"name": st.name, "command": st.command, "start": st.start, "samples": 0,
                               "steps": st.steps, "done": False})
                continue
            cfg = json.loads((run / "config.json").read_text())
            start = json.loads((run / "start.json").read_text()) if (run / "start.json").is_file() else {}
            done = latest["timesteps"] >= st.steps
            entry = {"name": st.name, "command": st.command, **start,
                     "config_sha256": config_sha256(load_run_config(run)[0]),
                     "samples": latest["timesteps"], "steps": st.steps, "done": done, "wall_s": latest["wall_s"],
                     "git_commit": cfg.get("git_commit"), "started": cfg.get("started")}
            if done:
                ck = _final_checkpoint(run, latest)
                entry.update(end_checkpoint=ck.name, end_sha256=sha256(ck))
            stages.append(entry)
        return {"recipe": self.recipe.name, "file": shown(self.path), "sha256": sha256(self.path),
                "git_commit": git_commit(), "written": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
                "stages": stages}

    def write_manifest(self) -> dict:
        m = self.manifest()
        self.folder.mkdir(parents=True, exist_ok=True)
        tmp = self.folder / "manifest.tmp.json"
        tmp.write_text(json.dumps(m, indent=2) + "\n")
        tmp.replace(self.folder / "manifest.json")
        return m

    # ------------------------------------------------------------------------------- running
    def run(self, only: str | None = None, chunk: int | None = None, progress: bool = True) -> int:
        """Run (or resume) the stages in order, or only ``only``; at most ``chunk`` more samples.

        :raises RecipeError: a start or a run folder that does not fit the recipe.
        """
        from racecav.training.train import new_run, run_dagger, train_ppo

        budget = chunk
        stages = [self.recipe.stage(only)] if only else self.recipe.stages
        for st in stages:
            run = self.run_dir(st)
            latest = _latest(run)
            tc = st.train_config()
            if latest is not None:
                check_run_config(run, st)
                if latest["timesteps"] >= st.steps:
                    log.info("stage %s: done (%d samples)", st.name, latest["timesteps"])
                    continue
                tc, state, resume = load_run_config(run)[0], latest, True
                started = json.loads((run / "start.json").read_text()) if (run / "start.json").is_file() else {}
                if started.get("scenarios_sha256") != (now := scenarios_sha256(tc)):
                    log.warning("stage %s: its scenarios (%s) are not the files it started with (another "
                                "generated suite?): scenarios_sha256 %s, now %s", st.name, tc.env.scenarios,
                                started.get("scenarios_sha256"), now)
            else:
                start, digest = self.start_of(st)
                data = scenarios_sha256(tc)  # before the run folder: a missing suite leaves none
                tc = tc.model_copy(update={"init_from": str(start)})
                state = new_run(tc, run)
                if state is None:
                    return 2
                (run / "start.json").write_text(json.dumps(
                    {"start": st.start, "start_path": shown(start), "start_sha256": digest,
                     "scenarios_sha256": data}, indent=2) + "\n")
                resume = False
            before = state["timesteps"]
            total = st.steps if budget is None else min(st.steps, before + budget)
            log.info("stage %s: %s from %d to %d samples (of %d)", st.name, "resumed" if resume else "started",
                     before, total, st.steps)
            train = run_dagger if st.command == "dagger" else train_ppo
            try:
                rc = train(run, tc, state, total, resume=resume, progress=progress)
            finally:
                self.write_manifest()
            if rc:
                return rc
            after = json.loads((run / "latest.json").read_text())["timesteps"]
            if after < total:  # stopped by a signal
                return 0
            if budget is not None:
                budget -= after - before
            if after < st.steps or (budget is not None and budget <= 0):
                log.info("stage %s: %d of %d samples; run the command again to go on", st.name, after, st.steps)
                return 0
        self.write_manifest()
        return 0

    def record(self, dest: Path) -> Path:
        """Copy the manifest, each stage's config.json (init_from spelled as the recipe's start) and
        progress.csv, and each finished stage's final checkpoint (+ .vecnorm.pkl) into ``dest``."""
        m = self.write_manifest()
        dest = Path(dest)
        for st, entry in zip(self.recipe.stages, m["stages"]):
            run = self.run_dir(st)
            if entry.get("from") == "record" or _latest(run) is None:
                continue
            out = dest / st.name
            out.mkdir(parents=True, exist_ok=True)
            cfg = json.loads((run / "config.json").read_text())
            cfg["init_from"] = st.start  # not this machine's path
            (out / "config.json").write_text(json.dumps(cfg, indent=2) + "\n")
            for name in ("progress.csv", "curriculum.csv"):
                if (run / name).is_file():
                    shutil.copyfile(run / name, out / name)
            if entry["done"]:
                ck = _final_checkpoint(run, _latest(run))
                shutil.copyfile(ck, out / entry["end_checkpoint"])
                if ck.with_suffix(".vecnorm.pkl").is_file():
                    shutil.copyfile(ck.with_suffix(".vecnorm.pkl"),
                                    (out / entry["end_checkpoint"]).with_suffix(".vecnorm.pkl"))
        dest.mkdir(parents=True, exist_ok=True)
        (dest / "manifest.json").write_text(json.dumps(m, indent=2) + "\n")
        return dest


def recipe_record(spec: str, run_dir: Path) -> dict:
    """What a shipped policy's metadata says of the recipe that built the run ``run_dir`` (a stage
    folder, ROOT/NAME/STAGE): name, file, the file's sha256 and the stage.

    :raises RecipeError: the folder is not a stage of the recipe, or not with its settings.
    """
    path = resolve(spec)
    recipe = load_recipe(path)
    run_dir = Path(run_dir)
    names_ = [st.name for st in recipe.stages]
    if run_dir.name not in names_:
        raise RecipeError(f"--recipe {spec}: {run_dir} is not a stage folder of the recipe ({', '.join(names_)})")
    check_run_config(run_dir, recipe.stage(run_dir.name))
    return {"name": recipe.name, "file": shown(path), "sha256": sha256(path), "stage": run_dir.name}


# ----------------------------------------------------------------------------------- CLI
def add_subcommands(sub) -> None:
    help_ = "rebuild a policy by its recipe (training/recipes/NAME.toml): each stage resumable, in chunks"
    p = sub.add_parser("recipe", help=help_, description=help_)
    p.add_argument("recipe", metavar="NAME_OR_PATH", help="a recipe name (training/recipes/NAME.toml) or a .toml file")
    p.add_argument("--stage", help="run only this stage")
    p.add_argument("--chunk-steps", type=lambda v: int(float(v)), metavar="N",
                   help="run at most N more samples (rounded up to whole rollouts), then stop after a "
                        "checkpoint (run again to go on)")
    p.add_argument("--root", type=Path, default=ROOT, help=f"where the stages run: ROOT/NAME/STAGE (default {ROOT})")
    p.add_argument("--no-progress", action="store_true", help="no tqdm bar")
    p.add_argument("--record", nargs="?", const="", metavar="DIR", type=str,
                   help="copy the manifest, stage records and finished stages' weights into DIR "
                        "(default training/recipes/NAME/, committed) instead of training")


def run(args, cfg) -> int:
    if args.chunk_steps is not None and args.chunk_steps < 1:
        print("racecav train recipe: --chunk-steps: must be >= 1")
        return 2
    path = resolve(args.recipe)
    try:
        recipe = load_recipe(path)
        runner = Runner(recipe, path, args.root)
        if args.record is not None:
            dest = runner.record(Path(args.record) if args.record else runner.record_dir)
            print(f"recorded {recipe.name} in {dest}")
            return 0
        rc = runner.run(args.stage, args.chunk_steps, progress=not args.no_progress)
    except RecipeError as e:
        print(f"racecav train recipe: {e}")
        return 2
    if rc == 0:
        print(f"{recipe.name}: manifest {runner.folder / 'manifest.json'}")
    return rc
