"""The roads benchmark (evaluation/benchmark.py, common/data/suites/roads.toml, docs/world.md):

- ``[[ways]]`` and inline ``[map]`` worlds: curbs cut where they lie inside another road or way;
  unknown or broken fields named;
- the generator's splits: disjoint seeds, reproducible bytes, the ood bands held out of train and
  test and drawn by every ood file;
- the non-evading references on fresh trials: <= 5 % success on the conflicts, >= 95 % on the
  controls;
- both backends give the same contact step (+-1 control period) on a generated world of every shape;
- a synchronised actor goes on at its nominal speed once the ego has stood still (release_stopped_s).
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
import tomllib

import numpy as np
import pytest

from racecav.common.scenario import Scenario, load_scenario
from racecav.common.world import WorldFile, build_world
from racecav.evaluation import benchmark as B

SMALL = ["crossing", "merge", "rear-braking", "stop-short", "oncoming"]
"""The families of the generated sample (merge draws the held-out Y-junction in ood)."""


def _inside(p, quad) -> bool:
    """Strictly inside a convex quadrilateral (1 mm)."""
    q = np.asarray(quad)
    area = sum(q[k, 0] * q[(k + 1) % 4, 1] - q[(k + 1) % 4, 0] * q[k, 1] for k in range(4))
    sgn = 1.0 if area > 0 else -1.0
    for k in range(4):
        e = q[(k + 1) % 4] - q[k]
        if sgn * (e[0] * (p[1] - q[k][1]) - e[1] * (p[0] - q[k][0])) < 1e-3:
            return False
    return True


def test_t_junction_cuts_the_curb_it_joins_and_its_own_inside_the_road():
    w = build_world(WorldFile.model_validate({
        "name": "t", "kind": "roads", "lane_width": 2.0,
        "roads": [{"cx": 0, "cy": 0, "yaw_deg": 0, "length": 20, "width": 2.0}],
        "ways": [{"x": 0, "y": 0, "yaw_deg": 90, "width": 1.6, "pieces": [{"straight": 6}]}]}))
    walls = np.asarray(w.walls, float)
    right = walls[np.isclose(walls[:, 1], -1.0) & np.isclose(walls[:, 3], -1.0)]
    left = walls[np.isclose(walls[:, 1], 1.0) & np.isclose(walls[:, 3], 1.0)]
    assert len(right) == 1 and np.isclose(abs(right[0, 2] - right[0, 0]), 20.0)  # the far curb is whole
    xs = sorted(np.concatenate([left[:, 0], left[:, 2]]).round(4))
    assert xs == [-10.0, -0.8, 0.8, 10.0]  # the near curb is open over the side road's width
    side = walls[np.isclose(np.abs(walls[:, 0]), 0.8) & np.isclose(walls[:, 0], walls[:, 2])]
    assert len(side) == 2 and np.allclose(np.sort(side[:, [1, 3]], axis=1), [[1.0, 6.0]] * 2)  # from the curb on


def test_way_walls_never_lie_inside_another_road():
    """A bend that crosses the ego's road: no wall point inside another road or way."""
    from racecav.common.world import way_edges

    bf = B.load_benchmark("roads")
    for seed in range(4):
        ctx = B.Ctx(np.random.default_rng(seed), bf.common, bf.ood)
        m = B.draw_map(ctx, "bend")
        f = WorldFile.model_validate(m.world)
        walls = np.asarray(build_world(f).walls, float)
        assert len(walls) > 10
        from racecav.common.world import _road_quad

        left, right = way_edges(f.ways[0], f.arc_max_step_deg)
        way_quads = [np.array([right[k], right[k + 1], left[k + 1], left[k]]) for k in range(len(left) - 1)]
        road = _road_quad(f.roads[0])
        for x0, y0, x1, y1 in walls:
            for u in np.linspace(0, 1, 7):
                p = (x0 + (x1 - x0) * u, y0 + (y1 - y0) * u)
                on_road_curb = abs(abs(p[1]) - f.roads[0].width / 2) < 1e-4
                if on_road_curb:
                    assert not any(_inside(p, q) for q in way_quads), p
                else:
                    assert not _inside(p, road), p


def test_inline_map_and_bad_fields_are_named(tmp_path):
    base = {"name": "x", "duration_s": 5.0, "ego": {"x": -3.0, "y": -0.5, "yaw_deg": 0.0},
            "success": {"min_progress_m": 1.0},
            "map": {"name": "m", "kind": "roads", "lane_width": 2.0,
                    "roads": [{"cx": 0, "cy": 0, "yaw_deg": 0, "length": 20, "width": 2.0}],
                    "ways": [{"x": 0, "y": 0, "yaw_deg": 60, "width": 2.0, "pieces": [{"straight": 5}]}]}}
    sc = Scenario.model_validate(base)
    assert sc.build_world().walls.shape[0] == 5 and sc.world_key.startswith("map:")
    bad = json.loads(json.dumps(base))
    bad["map"]["ways"][0]["widht"] = 1.0
    import tomli_w

    p = tmp_path / "bad.toml"
    p.write_text(tomli_w.dumps(bad))
    with pytest.raises(ValueError, match=r"map\.ways\.0\.widht"):
        load_scenario(p)
    both = dict(base, world="intersection")
    with pytest.raises(ValueError, match="world"):
        Scenario.model_validate(both)
    r = subprocess.run([sys.executable, "-m", "racecav.cli", "eval", "--scenario", str(p), "--controller", "scripted",
                        "--trials", "1"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "widht" in r.stdout + r.stderr


def test_bad_suite_fields_are_named(tmp_path):
    src = tomllib.loads((B.SUITES_DIR / "roads.toml").read_text())
    import tomli_w

    cases = [(("families", 0, "behavour"), "families.0.behavour"),
             (("ood", "width_m"), "ood.width_m"),
             (("families", 1, "shapes"), "families.1.shapes")]
    for (*where, key), name in cases:
        d = json.loads(json.dumps(src))
        node = d
        for k in where:
            node = node[k]
        node[key] = [[1.0, 1.5]] if key == "width_m" else (["straight"] if key == "shapes" else "x")
        p = tmp_path / "s.toml"
        p.write_text(tomli_w.dumps(d))
        with pytest.raises(ValueError, match=name.replace(".", r"\.")):
            B.load_benchmark(p)
    r = subprocess.run([sys.executable, "-m", "racecav.cli", "suite", "generate", "--name", "roads", "--splits", "tst",
                        "--out", str(tmp_path / "o")], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "--splits" in r.stdout and len(r.stdout.strip().splitlines()) == 1


@pytest.fixture(scope="module")
def sample(tmp_path_factory):
    """A generated sample of five families (1 file per family and split, 2 in train)."""
    src = tomllib.loads((B.SUITES_DIR / "roads.toml").read_text())
    src["families"] = [f for f in src["families"] if f["name"] in SMALL]
    bf = B.BenchmarkFile.model_validate(src)
    out = tmp_path_factory.mktemp("roads")
    man = B.generate(bf, out, seed=4, progress=False, n_test=1, n_train=2)
    return bf, out, man


def test_splits_are_disjoint_and_reproducible(sample, tmp_path):
    bf, out, man = sample
    assert set(man["splits"]) == set(B.SPLITS)
    conflicts = [f for f in SMALL if not next(x for x in bf.families if x.name == f).control]
    for split, fams in (("train", SMALL), ("test", conflicts), ("ood", conflicts), ("controls", ["stop-short", "oncoming"])):
        assert sorted(e["family"] for e in man["splits"][split]) == sorted(f for f in fams for _ in range(2 if split == "train" else 1))
    seeds = {s: {tuple(e["seed"]) for e in man["splits"][s]} for s in B.SPLITS}
    for a in B.SPLITS:
        for b in B.SPLITS:
            assert a == b or not seeds[a] & seeds[b]
    assert set(man["redrawn"]) == set(B.SPLITS)
    B.generate(bf, tmp_path, seed=4, splits=("test",), progress=False, n_test=1, n_train=2)
    for e in man["splits"]["test"]:
        assert (out / e["file"]).read_bytes() == (tmp_path / e["file"]).read_bytes()


def _held_out(sc: Scenario, shape: str, ood: B.Ood) -> set[str]:
    """The held-out bands a generated file draws from, read from the file itself."""
    inb = lambda v, bands: any(a - 1e-6 <= v <= b + 1e-6 for a, b in bands)  # noqa: E731
    held = set()
    if shape in ood.shapes:
        held.add("shape")
    if inb(sc.map.lane_width, ood.width_m):
        held.add("width_m")
    if shape == "cross" and inb(sc.map.roads[1].yaw_deg % 180, ood.angle_deg):
        held.add("angle_deg")
    moving = [o for o in sc.obstacles if o.sync is not None]
    if moving and all(inb(o.speed, ood.actor_speed) and o.sync.speed_min >= ood.actor_speed[0][0] for o in moving):
        held.add("actor_speed")
    return held


def test_ood_bands_are_held_out_of_train_and_test(sample):
    bf, out, man = sample
    for split in B.SPLITS:
        for e in man["splits"][split]:
            sc = load_scenario(out / e["file"])
            held = _held_out(sc, e["shape"], bf.ood)
            if split == "ood":
                assert e["held_out"] in held | ({"angle_deg"} if e["shape"] == "bend" else set()), (e, held)
            else:
                assert not held, (e, held)
                for o in sc.obstacles:
                    assert o.speed <= 2.5 + 1e-6 and (o.sync is None or o.sync.speed_max <= 2.5 + 1e-6)


def test_references_on_fresh_trials(sample):
    """Fresh seeds and no start shift, whole durations: the conflicts make both references
    collide (<= 5 % success), the controls are passed (>= 95 %)."""
    _, out, man = sample
    for split, lo, hi in (("test", 0.0, 0.05), ("ood", 0.0, 0.05), ("controls", 0.95, 1.0)):
        scs = [load_scenario(out / e["file"]) for e in man["splits"][split]]
        _, ok = B.reference_outcomes(scs, trials=4, seed=2024, shifts=(0.0,), until_end=True)
        assert lo <= ok.mean() <= hi, (split, ok.mean(axis=(1, 2)))


def _contact_step(step, n, seq):
    for k in range(n):
        if step(seq[k]):
            return k
    return None


@pytest.mark.parametrize("shape,family", [("straight", "rear_stationary"), ("cross", "crossing"), ("t", "merge"),
                                          ("y", "braking"), ("bend", "crossing")])
def test_contact_step_parity_on_generated_worlds(shape, family):
    """Recorded action sequences (straight at 1 m/s, full throttle, and full throttle steering
    into the junction's curbs) replayed in both backends on a generated world of each shape: the
    contact happens in the same control step, give or take one."""
    from racecav.common.vehicle import load_car, throttle_for_speed
    from racecav.sim.bullet_world import BulletWorld
    from racecav.sim.fast_world import FastWorld

    bf = B.load_benchmark("roads")
    fam = B.BFamily(name="f", behaviour=family, shapes=[shape])
    for seed in range(50):
        ctx = B.Ctx(np.random.default_rng([9, seed]), bf.common, B.Ood())
        try:
            d, m = B.draw(ctx, fam)
            break
        except B._Redraw:
            continue
    sc = Scenario.model_validate(B.scenario_data(d, m, fam, bf.common, f"parity-{shape}"))
    car = load_car()
    n = int(round(sc.duration_s / car.control_period_s))
    t1 = float(throttle_for_speed(1.0, car, car.agent_speed_scale))
    steer = np.tile([1.0, 0.0], (n, 1))
    steer[int(1.0 / car.control_period_s):, 1] = 0.6 if shape != "straight" else 0.3
    bw = BulletWorld(sc)
    hits = 0
    try:
        for seq in (np.tile([t1, 0.0], (n, 1)), np.tile([1.0, 0.0], (n, 1)), steer):
            bw.reset(seed=3)
            trial = bw.trial
            kb = _contact_step(lambda a: bool(bw.step(a)[2][0]), n, seq)
            fw = FastWorld(n_envs=1, scenarios=[sc])
            fw.reset(seed=0)
            fw.place_trial(0, 0, trial)
            kf = _contact_step(lambda a: bool(fw.step(a[None])[2][0]), n, seq)
            assert (kb is None) == (kf is None), (kb, kf)
            if kb is not None:
                hits += 1
                assert abs(kb - kf) <= 1, (kb, kf)
    finally:
        bw.close()
    assert hits >= 2  # the conflict and the curb are met, not missed alike


def test_synchronised_actor_goes_on_once_the_ego_has_stood():
    from racecav.common.scenario import Sync, StartTrigger, TrialObstacle
    from racecav.sim.actors import ActorBatch

    sync = Sync(ego_point=(0.0, 0.0), actor_point=(0.0, -1.0), speed_min=0.2, speed_max=2.0,
                release_distance_m=0.5, release_time_s=0.5, release_stopped_s=1.0)
    o = TrialObstacle(x=0.0, y=-5.0, yaw=math.pi / 2, speed=1.5, start=StartTrigger(kind="time", value=0.0), sync=sync)
    ab = ActorBatch(1, 1)
    ab.load(0, [o])
    ego = np.array([[-4.0, 0.0, 0.0, 0.0]])  # standing 4 m before its point
    speeds = []
    for _ in range(40):  # 2 s of 0.05 s control periods
        ab.control(ego)
        for _ in range(4):
            ab.advance(0.0125)
        speeds.append(float(ab.v[0, 0]))
    assert speeds[5] == pytest.approx(0.2)  # crawling while the ego stands ...
    assert speeds[-1] == pytest.approx(1.5) and ab.released[0, 0]  # ... then on at its speed
    ab.load(0, [TrialObstacle(**{**o.__dict__, "sync": sync.model_copy(update={"release_stopped_s": None})})])
    for _ in range(40):
        ab.control(ego)
        ab.advance(0.05)
    assert ab.v[0, 0] == pytest.approx(0.2)  # default: it keeps crawling (the conflict suite's files)
