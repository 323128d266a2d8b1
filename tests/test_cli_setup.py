"""Every bad set-up of the CLI exits 2 with one line naming the option, field or path and the
rule (issue 60). The cases are found, not listed: every configuration field (through the
environment and a TOML file), every typed option of every command and subcommand, every option
that sets a configuration field, plus bad paths and devices. In-process (``racecav.cli.main``):
nothing is started, so the walk takes seconds."""

from __future__ import annotations

import argparse
import functools
import json
import os
import re
from pathlib import Path

import pytest
from pydantic import BaseModel, ValidationError

from racecav import cli
from racecav.common import procs
from racecav.common.config import Config, ConfigError, load_config, override

BAD = [{"bad": {"x": 1}}, "not-a-dict-or-number"]
"""Candidate bad values of a field: a map where none is expected, a word where a map is."""


_BUILD = cli.build_parser


@functools.lru_cache(maxsize=1)
def parser() -> argparse.ArgumentParser:
    return _BUILD()  # ~0.1 s to build, once: parse_args leaves the parser as it was


@pytest.fixture(autouse=True)
def clean_env(monkeypatch):
    for k in list(os.environ):
        if k.startswith("RACECAV_"):
            monkeypatch.delenv(k)
    monkeypatch.setattr(procs, "install_cleanup", lambda: None)  # no signal handlers in pytest
    monkeypatch.setattr(cli, "build_parser", parser)


def run(capsys, *argv: str) -> tuple[int, list[str]]:
    """racecav ARGV in-process: exit code and the lines it printed (log lines aside)."""
    try:
        rc = cli.main(list(argv))
    except SystemExit as e:  # argparse
        rc = e.code
    out = capsys.readouterr()
    lines = [ln for ln in (out.out + out.err).splitlines() if ln.strip() and " INFO " not in ln]
    return rc, lines


def fields(model: type[BaseModel], prefix: tuple[str, ...] = ()):
    """Dotted paths of every leaf field of the configuration (sections and subsections walked)."""
    for name, f in model.model_fields.items():
        ann = f.annotation
        if isinstance(ann, type) and issubclass(ann, BaseModel):
            yield from fields(ann, prefix + (name,))
        else:
            yield prefix + (name,)


def nest(path: tuple[str, ...], value) -> dict:
    d = value
    for p in reversed(path):
        d = {p: d}
    return d


def bad_value(path: tuple[str, ...]):
    for v in BAD:
        try:
            Config.model_validate(nest(path, v))
        except ValidationError:
            return v
    raise AssertionError(f"no bad value found for {'.'.join(path)}")


def toml_value(v) -> str:
    return "{ bad = { x = 1 } }" if isinstance(v, dict) else json.dumps(v)


def test_every_config_field_bad_in_env_and_file_is_one_line(capsys, monkeypatch, tmp_path):
    paths = list(fields(Config))
    assert len(paths) > 150  # the walk reaches every section
    for path in paths:
        v = bad_value(path)
        dotted = ".".join(path)
        var = "RACECAV_" + "__".join(p.upper() for p in path)
        monkeypatch.setenv(var, json.dumps(v))
        rc, lines = run(capsys, "state")
        monkeypatch.delenv(var)
        assert rc == 2 and len(lines) == 1, (var, rc, lines)
        # the field, or the key under it that is wrong (a sub-model field such as env.perturb)
        assert re.search(rf"{var}(__\w+)? \({re.escape(dotted)}(\.\w+)?\): ", lines[0]), lines
        assert "Traceback" not in lines[0], lines

        f = tmp_path / "bad.toml"
        f.write_text(f"[{'.'.join(path[:-1])}]\n{path[-1]} = {toml_value(v)}\n")
        rc, lines = run(capsys, "--config", str(f), "state")
        assert rc == 2 and len(lines) == 1, (dotted, rc, lines)
        assert re.search(rf"config file {re.escape(str(f))}: {re.escape(dotted)}(\.\w+)?: ", lines[0]), lines


def subparsers(parser: argparse.ArgumentParser, prefix: tuple[str, ...] = ()):
    """(command words, parser) of every command and subcommand."""
    yield prefix, parser
    for a in parser._actions:
        if isinstance(a, argparse._SubParsersAction):
            for name, sub in a.choices.items():
                yield from subparsers(sub, prefix + (name,))


def test_every_typed_option_refuses_a_bad_value_in_one_line(capsys):
    n = 0
    for words, sub in subparsers(parser()):
        for a in sub._actions:
            if not a.option_strings or a.nargs == 0:
                continue
            if a.choices is not None:
                bad = "not-a-choice"
            elif a.type not in (None, str, Path) and callable(a.type):
                bad = "x"  # every typed option here is a number
            else:
                continue
            flag = a.option_strings[-1]
            rc, lines = run(capsys, *words, flag, bad)
            assert rc == 2 and len(lines) == 1, (words, flag, rc, lines)
            assert flag in lines[0] and ("invalid" in lines[0] or "choice" in lines[0]), lines
            n += 1
    assert n > 100  # the walk reaches every command


def test_every_option_that_sets_a_config_field_names_both(capsys):
    """`--v-ref -1` -> `racecav baseline: --v-ref (baseline.v_ref): Input should be greater than
    or equal to 0 (got -1.0)`: options are validated as their configuration fields are."""
    import importlib

    checked = []
    for cmd, (module, _help) in cli.COMMANDS.items():
        mod = importlib.import_module(module)
        options = getattr(mod, "OPTIONS", None)
        if not options:
            continue
        actions = {a.dest: a for a in dict(subparsers(parser()))[(cmd,)]._actions}
        for dest, field in options.items():
            a = actions[dest]  # every mapped option exists
            if a.type not in (int, float):
                continue  # choices: argparse's own check (above); free text: any value is valid here
            bad = next((v for v in (-1, -10**12, 10**12, 0) if _refused(mod.SECTION, field, a.type(v))), None)
            if bad is None:
                continue  # no number this field refuses
            flag = "--" + dest.replace("_", "-")
            rc, lines = run(capsys, cmd, flag, str(a.type(bad)))
            assert rc == 2 and len(lines) == 1, (cmd, flag, rc, lines)
            assert f"{flag} ({mod.SECTION}.{field}): " in lines[0] and "(got " in lines[0], lines
            checked.append(flag)
    rc, lines = run(capsys, "baseline", "--v-ref", "-1")
    assert lines == ["racecav baseline: --v-ref (baseline.v_ref): Input should be greater than or equal to 0 "
                     "(got -1.0)"]
    assert len(checked) >= 8, checked


def _refused(section: str, field: str, value) -> bool:
    try:
        override(load_config(environ={}), section, {field: value})
    except ConfigError:
        return True
    return False


def test_bad_paths_and_devices_are_one_line(capsys, tmp_path):
    a_file = tmp_path / "a-file"
    a_file.write_text("")
    cases = [
        (["--config", str(tmp_path / "missing.toml"), "state"], "missing.toml"),
        (["--config", str(tmp_path), "state"], str(tmp_path)),
        (["actuator", "--neutral", "--port", str(tmp_path / "no-vesc")], "no-vesc"),
        (["deploy", "credentials", "--dir", str(a_file / "creds")], "creds"),
        (["policy", "--model", str(tmp_path / "missing.npz")], "missing.npz"),
        (["sim", "--scenario", str(tmp_path / "missing.toml")], "missing.toml"),
        (["replay", str(tmp_path / "missing.mcap")], "missing.mcap"),
        (["record", "-o", str(a_file / "run.mcap")], "a-file"),
        (["eval", "--scenario", "head-to-head", "--controller", "drl-avoid", "--out-dir", str(a_file / "out")],
         "out"),
        (["demo", "--out-dir", str(a_file / "out")], "out"),
    ]
    for argv, name in cases:
        rc, lines = run(capsys, *argv)
        assert rc == 2 and len(lines) == 1, (argv, rc, lines)
        assert name in lines[0] and "Traceback" not in lines[0], (argv, lines)
