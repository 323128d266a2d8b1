"""``racecav train``: the command line of training (the runs themselves: training/train.py).

    racecav train racing   [--steps N] [--run-dir DIR] [--resume] [--preset paper|fast] [...]
    racecav train overtake --heading default|reversed [--driver policy:racing] [...]
    racecav train dagger   --init-from POLICY.zip [...]  (imitate the yield teacher, training/dagger.py)
    racecav train recipe   NAME [--chunk-steps N]          (a policy's stages from a recipe, training/recipe.py)
    racecav train select   --run-dir DIR [--trials N]      (training/select.py)
    racecav train ship     --run-dir DIR --checkpoint STEP --name racing|default|reversed
    racecav train report                                   (docs/training.md)

Every setting is a flag made from a field of TrainConfig / EnvConfig (common/config.py).
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from racecav.training.flags import DAGGER_FLAGS, ENV_FLAGS, TRAIN_FLAGS, config_from_args, stage_defaults
from racecav.training.train import new_run, resume_run, run_dagger, train_ppo

log = logging.getLogger("racecav.train")

RUNS_DIR = Path("runs")


def _flag_type(annotation):
    """argparse type of a config field: ints accept 1e6, optional fields their inner type."""
    inner = [a for a in getattr(annotation, "__args__", (annotation,)) if a is not type(None)]
    t = inner[0] if inner else str
    if t is int:
        return lambda v: int(float(v))
    return t if t in (float, str) else str


def field_help(model, name: str, key: str, defaults: dict, fast: dict) -> str:
    """A config field's flag help: its docstring and its default for the stage (and under
    ``--preset fast`` where that differs)."""
    value = defaults[key]
    text = f"{model.model_fields[name].description} (default {value if value != {} else '{}'}"
    return text + (f"; --preset fast: {fast[key]})" if fast[key] != value else ")")


def add_config_flags(p, model, names, defaults: dict, fast: dict, dest=lambda n: n, flags=None,
                     prefix: str = "") -> None:
    """One flag per config field: type, help and default from common/config.py."""
    for name in names:
        f = model.model_fields[name]
        flag = (flags or {}).get(name, "--" + name.replace("_", "-"))
        alias = ("--lr",) if name == "learning_rate" else ()
        help_ = field_help(model, name, prefix + name, defaults, fast)
        if f.annotation is bool:
            p.add_argument(flag, *alias, dest=dest(name), action=argparse.BooleanOptionalAction, default=None,
                           help=help_)
        else:
            p.add_argument(flag, *alias, dest=dest(name), type=_flag_type(f.annotation), help=help_)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from racecav.common.config import TRAIN_PRESETS, EnvConfig, TrainConfig

    sub = parser.add_subparsers(dest="train_cmd", required=True, metavar="STAGE")

    def add_flags(p, stage: str) -> None:
        defaults, fast = stage_defaults(stage, "paper"), stage_defaults(stage, "fast")
        p.add_argument("--steps", type=float, default=1e6, help="total samples of the run (default 1e6)")
        p.add_argument("--run-dir", type=Path, help="run folder (default runs/<stage>[-<heading>])")
        p.add_argument("--resume", action="store_true", help="continue the run in --run-dir from latest")
        p.add_argument("--preset", choices=list(TRAIN_PRESETS), default="paper",
                       help="paper (the paper's PPO setting, one env) | fast (64 batched envs; docs/training.md) "
                            "(default paper)")
        p.add_argument("--no-progress", action="store_true", help="no tqdm bar")
        # every setting is a field of TrainConfig / EnvConfig (common/config.py): flags, help,
        # defaults and the run record come from there
        add_config_flags(p, TrainConfig, TRAIN_FLAGS, defaults, fast)
        add_config_flags(p, EnvConfig, ENV_FLAGS, defaults, fast, dest=lambda n: f"env_{n}", flags=ENV_FLAGS,
                         prefix="env.")
        return defaults, fast

    stages = {}  # their parsers: racecav train sweep checks its trials' flags with them
    for stage, help_ in (("racing", "stage 1: the racing policy on the empty track (0 obstacles)"),
                         ("overtake", "stage 2: overtaking among obstacle cars (and scenario episodes)")):
        p = stages[stage] = sub.add_parser(stage, help=help_, description=help_)
        add_flags(p, stage)
        p.set_defaults(stage=stage)
    help_ = "the yield teacher fitted by DAgger on the overtake env (training/dagger.py): the shipped avoid's recipe"
    p = stages["dagger"] = sub.add_parser("dagger", help=help_, description=help_)
    defaults, fast = add_flags(p, "dagger")
    add_config_flags(p, TrainConfig, DAGGER_FLAGS, defaults, fast)
    p.set_defaults(stage="dagger")
    from racecav.training import select  # cheap: argument definitions only

    select.add_subcommands(sub)
    from racecav.training import sweep

    sweep.add_subcommands(sub, stages)
    from racecav.training import recipe

    recipe.add_subcommands(sub)
    from racecav.training import robust_select

    robust_select.add_subcommands(sub)
    p = sub.add_parser("export", help="write a policy as ONNX: DIR/model.onnx + model.json (ray layout, "
                       "normalisation, action meaning); run it with racecav policy --backend onnxruntime")
    p.add_argument("--onnx", required=True, metavar="NAME", help="racing | default | reversed | PATH to a policy .npz")
    p.add_argument("--out", type=Path, help="output folder (default runs/onnx/NAME)")
    p.add_argument("--car", default="slash", help="car file (lidar layout, steering mapping in the sidecar) (default slash)")
    p.set_defaults(stage="export")


def run(args, cfg) -> int:
    if args.train_cmd in ("racing", "overtake"):
        return train(args, cfg)
    if args.train_cmd == "dagger":
        return train_dagger(args, cfg)
    if args.train_cmd == "export":
        return export_onnx(args)
    if args.train_cmd == "recipe":
        from racecav.training import recipe

        return recipe.run(args, cfg)
    if args.train_cmd == "sweep":
        from racecav.training import sweep

        return sweep.run(args, cfg)
    if args.train_cmd == "robust-select":
        from racecav.training import robust_select

        return robust_select.run(args, cfg)
    from racecav.training import select

    return select.run(args, cfg)


def export_onnx(args) -> int:
    """``racecav train export --onnx NAME``: services/policy/onnx_export.py does the work."""
    try:
        from racecav.services.policy.onnx_export import export
    except ImportError as e:
        print(f"racecav train export: {e} (pip install 'racecav[onnx]')")
        return 2
    out = args.out or RUNS_DIR / "onnx" / Path(args.onnx).stem
    try:
        model, meta = export(args.onnx, out, args.car)
    except ImportError as e:
        print(f"racecav train export: {e} (pip install 'racecav[onnx]')")
        return 2
    except (ValueError, FileNotFoundError) as e:
        print(f"racecav train export: {e}")
        return 2
    print(f"wrote {model} and {meta}")
    return 0


def train(args, cfg) -> int:
    heading = args.env_heading or "default"
    run_dir = Path(args.run_dir or RUNS_DIR / (args.stage if args.stage == "racing" else f"overtake-{heading}"))
    opened = open_run(args, cfg, run_dir)
    if opened is None:
        return 2
    return train_ppo(run_dir, *opened, int(args.steps), resume=args.resume, progress=not args.no_progress)


def open_run(args, cfg, run_dir: Path):
    """(TrainConfig, latest state) of the run in ``run_dir``: read back with ``--resume``, else
    made from the flags and recorded in a new config.json. None (after saying why) if neither."""
    if args.resume:
        return resume_run(run_dir)
    if (run_dir / "latest.zip").exists():
        log.error("%s already holds a run: use --resume or another --run-dir", run_dir)
        return None
    try:
        tc = config_from_args(args, cfg.env if cfg is not None else None)
    except ValueError as e:
        print(f"racecav train: {e}")
        return None
    state = new_run(tc, run_dir)
    return None if state is None else (tc, state)


def train_dagger(args, cfg) -> int:
    """``racecav train dagger``: a run folder as train()'s, the policy fitted by training/dagger.py."""
    run_dir = Path(args.run_dir or RUNS_DIR / "dagger")
    opened = open_run(args, cfg, run_dir)
    if opened is None:
        return 2
    return run_dagger(run_dir, *opened, int(args.steps), resume=args.resume, progress=not args.no_progress)
