"""The dependency direction: common <- sim <- services, training, evaluation <- cli.

Imports of racecav modules, at module level or inside functions, point only downward, form no
cycle (an import inside a function would hide one at run time), and every module imports.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LAYERS = {"common": 0, "sim": 1, "services": 2, "training": 2, "evaluation": 2, "deploy": 2, "racecav": 3}
"""Package folder -> layer; a module may import its own layer's folder and lower layers."""
ALLOWED_SIDEWAYS = {
    ("training", "services"),  # `racecav train export --onnx` writes the policy service's ONNX model
    ("services", "training"),  # `racecav bench safety` drives laps in the training world
    ("training", "evaluation"),  # selection and the report run evaluation/inprocess.py's trial loops
    ("evaluation", "training"),  # evaluation/inprocess.py's fast-world runner steps the batched VecEnv
}
"""(importer, imported) pairs of the same layer that are allowed."""
FOLDERS = ("common", "sim", "services", "training", "evaluation", "deploy", "racecav")


def _modules() -> list[tuple[str, Path]]:
    out = []
    for folder in FOLDERS:
        for f in sorted((ROOT / folder).rglob("*.py")):
            if "__pycache__" in f.parts:
                continue
            rel = f.relative_to(ROOT / folder).with_suffix("")
            parts = [] if folder == "racecav" else [folder]
            name = ".".join(["racecav", *parts, *rel.parts]).removesuffix(".__init__")
            out.append((name, f))
    return out


def _folder(module: str) -> str | None:
    parts = module.split(".")
    if parts[0] != "racecav":
        return None
    if len(parts) == 1 or parts[1] in ("cli", "__main__"):
        return "racecav"
    return parts[1] if parts[1] in LAYERS else None


def test_imports_point_downward():
    bad = []
    for name, path in _modules():
        src = _folder(name)
        for node in ast.walk(ast.parse(path.read_text())):
            targets = []
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                targets = [node.module]
            elif isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            for t in targets:
                dst = _folder(t)
                if dst is None or dst == src:
                    continue
                if LAYERS[dst] > LAYERS[src] or (LAYERS[dst] == LAYERS[src] and (src, dst) not in ALLOWED_SIDEWAYS):
                    bad.append(f"{name} imports {t}")
    assert not bad, "\n".join(bad)


def _graph() -> dict[str, set[str]]:
    """Module -> racecav modules it imports (at module level or inside functions)."""
    mods = dict(_modules())
    graph: dict[str, set[str]] = {}
    for name, path in mods.items():
        deps = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                cands = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
            elif isinstance(node, ast.Import):
                cands = [a.name for a in node.names]
            else:
                continue
            deps |= {c for c in cands if c in mods and c != name}
        graph[name] = deps
    return graph


def test_no_import_cycles():
    """No loop between modules, counting imports inside functions (which hide loops at run time)."""
    graph, state, stack = _graph(), {}, []

    def visit(n):
        state[n] = 1
        stack.append(n)
        for d in sorted(graph[n]):
            if state.get(d) == 1:
                raise AssertionError("import cycle: " + " -> ".join(stack[stack.index(d):] + [d]))
            if d not in state:
                visit(d)
        stack.pop()
        state[n] = 2

    for n in sorted(graph):
        if n not in state:
            visit(n)


@pytest.mark.timeout(300)
def test_every_module_imports():
    """Every module imports (in one fresh interpreter): nothing refers to a moved or missing module."""
    names = [n for n, _ in _modules() if not n.endswith("__main__")]
    code = ("import importlib, sys\nbad = []\nfor n in sys.argv[1:]:\n    try:\n        importlib.import_module(n)\n"
            "    except Exception as e:\n        bad.append((n, repr(e)))\nprint(bad)\n")
    r = subprocess.run([sys.executable, "-c", code, *names], capture_output=True, text=True, timeout=280)
    assert r.stdout.strip().splitlines()[-1] == "[]", r.stdout + r.stderr
