"""The paper's facts and the project's names, in one place.

- the paper's three evaluation scenarios (and their conflict-timed versions), short labels;
- the paper's Table 1 (success, 10 hardware trials) and Table 2 (compute on a Jetson Orin AGX);
- the controllers ``racecav eval`` knows: the racecav command that runs each, its bus service,
  the shipped policy it needs, its label in tables.
Evaluation, training selection, the benchmarks and the CLI read these; nothing else spells them.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

PAPER_SCENARIOS = ("right-to-left", "head-to-head", "left-to-right")
"""Obstacle car from the ego's right, head-on, from its left (paper, Table 1 and Fig. 5)."""
SHORT = {"right-to-left": "R to L", "head-to-head": "H to H", "left-to-right": "L to R"}
CONFLICT_SCENARIOS = tuple(f"conflict-{s}" for s in PAPER_SCENARIOS)
"""The same three timed by the ego (common/data/scenarios/conflict-*.toml)."""

PAPER_TABLE1 = {
    "mpc-apf": (0.7, 0.1, 0.6),
    "drl-default": (0.8, 0.3, 0.7),
    "drl-reversed": (0.8, 0.6, 0.7),
}
"""Success rates per scenario (PAPER_SCENARIOS order), 10 hardware trials, obstacle at 1 m/s."""
PAPER_TABLE2 = {
    "policy": {"flops": 30_466, "ms": 0.206},
    "baseline": {"flops": 960_000, "ms": 13.2, "iterations": 12},
}
"""Compute per control step on the Jetson Orin AGX: the DRL MLP and the MPC-APF."""


@dataclass(frozen=True)
class ControllerSpec:
    """A controller ``racecav eval`` can run: the racecav command and what it needs."""

    name: str
    args: tuple[str, ...]
    """``racecav`` arguments of the command (a scripted program is filled in by the harness)."""
    service: str
    """Its service name on the bus (liveliness/status key)."""
    module: str
    """Python module of the command."""
    policy: str | None = None
    """Shipped policy it runs (common/data/policies/NAME.npz), if any."""
    label: str = ""
    charge_ms: float = 0.0
    """Lockstep: the compute time (ms) the sim charges each of its commands by default (so a cell
    does not change with the machine's load): its in-process median in docs/benchmarks.md
    (`racecav bench controllers`, 2026-11-30), see CHARGE_SOURCE."""
    model: Path | None = None
    """The weights file it needs, when resolved (the harness fills it in; ``--model`` overrides)."""


HOLD_SPEED = 1.0
"""m/s: the 'no evasion' reference holds the paper's scenarios' ego start speed."""

CONTROLLERS: dict[str, ControllerSpec] = {c.name: c for c in (
    ControllerSpec("drl-avoid", ("policy", "--model", "avoid"), "policy", "racecav.services.policy.service",
                   "avoid", "DRL avoid (trained on conflicts)", charge_ms=0.008),
    # The ablation's first row (docs/training.md): the paper's observation, action and reward,
    # trained with the conflict mix; what the paper's design reaches once it has seen conflicts.
    ControllerSpec("drl-avoid-paper", ("policy", "--model", "avoid-paper"), "policy",
                   "racecav.services.policy.service", "avoid-paper", "DRL paper design + conflict mix (ablation row 1)",
                   charge_ms=0.008),
    ControllerSpec("drl-reversed", ("policy", "--model", "reversed"), "policy", "racecav.services.policy.service",
                   "reversed", "DRL reversed heading", charge_ms=0.005),
    ControllerSpec("drl-default", ("policy", "--model", "default"), "policy", "racecav.services.policy.service",
                   "default", "DRL default", charge_ms=0.006),
    ControllerSpec("drl-racing", ("policy", "--model", "racing"), "policy", "racecav.services.policy.service",
                   "racing", "DRL racing (stage 1, not in the paper's table)", charge_ms=0.006),
    ControllerSpec("mpc-apf", ("baseline",), "baseline", "racecav.services.baseline.service", None, "MPC-APF",
                   charge_ms=2.313),
    # References without evasion: straight at the throttle that holds 1 m/s (the scenarios' ego
    # start speed: shows the scenarios are real conflicts), and straight at full throttle (the
    # agent's 2.7 m/s, about the DRL policies' speed: in the paper-timed side scenarios it is
    # through the crossing before the obstacle arrives). The baseline told to cruise at 2.7 m/s
    # shows the same.
    ControllerSpec("scripted", ("scripted", "--program", "HOLD"), "scripted", "racecav.services.sim.scripted",
                   None, "no evasion (straight 1 m/s, scripted)"),
    ControllerSpec("full-throttle", ("scripted", "--program", "1.0,0.0,100000000"), "scripted",
                   "racecav.services.sim.scripted", None, "no evasion (straight, full throttle, scripted)"),
    ControllerSpec("mpc-apf-fast", ("baseline", "--v-ref", "2.7"), "baseline", "racecav.services.baseline.service",
                   None, "MPC-APF at v_ref 2.7 m/s (not in the paper)", charge_ms=2.313),
)}
CHARGE_SOURCE = ("docs/benchmarks.md, section controllers (2026-11-30): in-process median per shipped policy "
                 "(`PolicyService.act`) and of the MPC-APF step; the scripted references compute nothing to "
                 "speak of (charged 0)")
"""Where each ControllerSpec.charge_ms comes from (printed in docs/results.md)."""
TABLE_CONTROLLERS = ("mpc-apf", "drl-default", "drl-reversed")
"""The paper's Table 1 rows."""
DEFAULT_TABLE = ("mpc-apf", "drl-default", "drl-reversed", "drl-avoid", "drl-avoid-paper", "scripted", "full-throttle", "mpc-apf-fast")
"""``racecav eval --table`` rows (a policy not shipped yet is left out)."""
