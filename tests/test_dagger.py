"""The privileged planner (training/expert.py) and ``racecav train dagger`` (training/dagger.py).

- the planner passes the conflict-timed paper scenarios that a straight car fails, only reads
  the world it plans for, and refuses traffic it cannot predict;
- the imitation loss ignores differences the actuation clips away;
- a dagger run writes a PPO run folder that resumes and that the selection loads.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from racecav.common.scenario import load_scenario, scenario_names
from racecav.sim.fast_world import FastWorld
from racecav.training.dagger import action_bounds, imitation_loss, mean_action
from racecav.training.expert import Expert
from tests.checkpoints_support import ROW16

CONFLICT = [n for n in scenario_names() if load_scenario(n).conflict_timed]


def test_planner_passes_the_conflict_timed_scenarios_and_only_reads_the_world():
    scs = [load_scenario(n) for n in CONFLICT]
    trials = 3
    fw = FastWorld(n_envs=len(scs) * trials, scenarios=scs, seed=5)
    fw.scenario_of_env = np.repeat(np.arange(len(scs)), trials)
    fw.reset()
    ex = Expert(fw)
    ended = np.zeros(fw.n_envs, bool)
    success = np.zeros(fw.n_envs, bool)
    first = True
    while not ended.all():
        before = (fw.x.copy(), fw.actors.s.copy(), fw.time.copy())
        a = ex.act()
        if first:  # planning steps copies of the world, never the world itself
            for b, now in zip(before, (fw.x, fw.actors.s, fw.time)):
                assert np.array_equal(b, now)
            first = False
        fw.step(a)
        over = ~ended & (fw.contact() | (fw.time >= fw.time_limit - 1e-9))
        success[over] = fw.success()[over]
        ended |= over
    assert success.all(), dict(zip(np.repeat(CONFLICT, trials), success))


def test_imitation_loss_ignores_what_the_actuation_clips():
    from racecav.common.vehicle import load_car

    lo, hi = (torch.as_tensor(b) for b in action_bounds(load_car("slash")))
    scale = torch.ones(2)
    label = torch.stack([hi, lo])  # full throttle + full left; coast + full right
    beyond = torch.stack([hi + 0.7, lo - 0.4])
    assert float(imitation_loss(beyond, label, lo, hi, scale)) == 0.0
    short = torch.stack([hi - 0.1, lo + 0.1])
    assert abs(float(imitation_loss(short, label, lo, hi, scale)) - 0.01) < 1e-6
    mid = torch.tensor([[0.5, 0.0]])
    assert abs(float(imitation_loss(mid + 0.2, mid, lo, hi, scale)) - 0.04) < 1e-6
    # with a brake (a_T < brake_below brakes) the throttle's bound is the action space's -1: a brake
    # label keeps its value and a coasting prediction is charged for it (it would coast, not brake)
    from racecav.common.vehicle import brake_from_action

    car = load_car("slash")
    blo, bhi = action_bounds(car, brake_below=-0.5)
    assert blo[0] == -1.0 and bhi[0] == 1.0 and blo[1] == lo[1]
    brake = torch.tensor([[float(np.clip(-1.0, blo[0], bhi[0])), 0.0]])
    assert brake_from_action(float(brake[0, 0]), -0.5)
    blo_t, bhi_t = torch.as_tensor(blo), torch.as_tensor(bhi)
    assert float(imitation_loss(torch.tensor([[0.0, 0.0]]), brake, blo_t, bhi_t, scale)) == pytest.approx(0.5)
    assert float(imitation_loss(torch.tensor([[-1.3, 0.0]]), brake, blo_t, bhi_t, scale)) == 0.0


def test_dagger_run_resumes_and_the_selection_loads_its_checkpoints(tmp_path, capsys):
    from racecav.cli import main
    from racecav.training.select import policy_from_checkpoint

    run = tmp_path / "run"
    base = ["train", "dagger", "--run-dir", str(run), "--no-progress"]
    flags = ["--preset", "fast", "--n-envs", "8", "--n-steps", "8", "--checkpoint-every", "64",
             "--grad-steps", "3", "--batch-size", "32", "--world", "figure8", "--heading", "reversed",
             "--n-obstacles", "4", "--driver", "centerline", "--scenarios", "common/data/scenarios/conflict-head-to-head.toml",
             "--scenario-share", "0.5", "--obs-stack", "2", "--lidar", "wide",
             "--init-from", ROW16, "--expert-horizon-s", "1.0"]
    assert main(base + flags + ["--steps", "128"]) == 0  # in-process: the torch import is paid once
    assert json.loads((run / "latest.json").read_text())["timesteps"] == 128
    assert main(base + ["--resume", "--steps", "192"]) == 0
    rows = (run / "progress.csv").read_text().splitlines()
    assert [int(x.split(",")[0]) for x in rows[1:]] == [64, 128, 192]
    cfg = json.loads((run / "config.json").read_text())
    assert cfg["stage"] == "dagger" and cfg["expert_horizon_s"] == 1.0
    pol = policy_from_checkpoint(run / "checkpoints" / "step_000000192.zip", obs_stack=2, lidar="wide")
    a = pol(np.full((1, 2 * 169), 5.0, np.float32))
    assert a.shape == (1, 2) and np.isfinite(a).all()
    # no --init-from: a clear refusal, no run folder
    assert main(["train", "dagger", "--run-dir", str(tmp_path / "x"), "--preset", "fast", "--steps", "64"]) == 2
    assert "--init-from" in capsys.readouterr().out
    assert not (tmp_path / "x" / "config.json").exists()


def test_dagger_with_yield_and_balance_counts_its_steering_round_a_car(tmp_path):
    """`racecav train dagger --expert yield --bc-balance`: the kind that gets half of each minibatch
    (progress.csv's manoeuvres) is the teacher's steering round a car, a share of its labels, not
    every relabelled step (on the head-to-head file every step is relabelled)."""
    import csv

    from racecav.cli import main

    run = tmp_path / "run"
    flags = ["train", "dagger", "--run-dir", str(run), "--no-progress", "--preset", "fast", "--n-envs", "8",
             "--n-steps", "8", "--checkpoint-every", "1000", "--grad-steps", "2", "--batch-size", "32",
             "--world", "figure8", "--heading", "reversed", "--n-obstacles", "4", "--driver", "centerline",
             "--scenarios", "common/data/scenarios/conflict-head-to-head.toml", "--scenario-share", "1.0",
             "--obs-stack", "2", "--lidar", "wide", "--brake-below", "-0.5", "--init-from", ROW16,
             "--expert", "yield", "--mirror-families", "conflict-head-to-head", "--expert-share", "1.0",
             "--bc-balance", "--steps", "384"]
    assert main(flags) == 0
    assert json.loads((run / "config.json").read_text())["bc_balance"] is True
    last = list(csv.DictReader((run / "progress.csv").open()))[-1]
    assert 0.0 < float(last["manoeuvres"]) < 0.5, last


def test_planner_refuses_traffic_it_cannot_predict():
    fw = FastWorld(n_envs=1, world="figure8", n_obstacles=2, driver=lambda obs: np.zeros((len(obs), 2)))
    with pytest.raises(ValueError, match="centerline"):
        Expert(fw)
    Expert(FastWorld(n_envs=1, world="figure8", n_obstacles=2, driver="centerline"))


def test_planner_plans_a_subset_as_it_plans_the_whole_batch():
    sc = load_scenario("conflict-left-to-right")
    fw = FastWorld(n_envs=4, scenarios=[sc], seed=2)
    fw.reset()
    for _ in range(5):
        fw.step(np.tile([1.0, 0.0], (4, 1)))
    whole, part = Expert(fw, horizon_s=1.0), Expert(fw, horizon_s=1.0, envs=[1, 3])
    assert np.array_equal(whole.scores()[[1, 3]], part.scores())
    assert part.act().shape == (2, 2)


def test_ppo_imitation_term_fits_the_planner_and_resumes(tmp_path):
    """``racecav train overtake --bc-coef``: the planner labels every world at bc_label_steps steps
    per rollout, the fit after each PPO update lowers the imitation loss on those labels, and
    imitation.csv continues across a resume."""
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import VecNormalize

    from racecav.cli import main
    from racecav.training.imitation_term import make_callback
    from racecav.training.runs import load_run_config
    from racecav.training.train import _ppo_kwargs, make_venv

    run = tmp_path / "run"
    base = ["train", "overtake", "--run-dir", str(run), "--no-progress"]
    flags = ["--preset", "fast", "--n-envs", "8", "--n-steps", "8", "--batch-size", "32", "--n-epochs", "1",
             "--checkpoint-every", "64", "--world", "figure8", "--heading", "reversed", "--n-obstacles", "4",
             "--driver", "centerline", "--scenarios", "common/data/scenarios/conflict-left-to-right.toml",
             "--scenario-share", "0.5", "--obs-stack", "2", "--lidar", "wide", "--init-from",
             ROW16, "--bc-coef", "1", "--bc-label-steps", "2", "--bc-grad-steps", "3",
             "--expert-horizon-s", "1.0"]
    assert main(base + flags + ["--steps", "128"]) == 0
    assert main(base + ["--resume", "--steps", "256"]) == 0
    with (run / "imitation.csv").open() as f:
        rows = [r.split(",") for r in f.read().splitlines()[1:]]
    # a fit after each update but the last: at 64 (labels of 8 worlds x 2 steps), then the
    # resumed run starts an empty aggregate (not checkpointed) and fits at 192
    assert [(int(r[0]), int(r[1])) for r in rows] == [(64, 16), (192, 16)], rows
    assert all(np.isfinite(float(r[2])) for r in rows)
    assert load_run_config(run)[0].bc_coef == 1.0
    # traffic the planner cannot predict: a clear refusal before any run folder is written
    bad = ["train", "overtake", "--run-dir", str(tmp_path / "x"), "--preset", "fast", "--steps", "64",
           "--driver", "policy:racing", "--bc-coef", "1"]
    assert main(bad) == 2 and not (tmp_path / "x" / "config.json").exists()

    # the fit itself: on a fresh model, the loss on the labels it fitted falls
    tc = load_run_config(run)[0].model_copy(update={"bc_coef": 10.0, "bc_grad_steps": 40})
    venv = VecNormalize(make_venv(tc, seed=3), norm_obs=True, norm_reward=True, gamma=tc.gamma)
    model = PPO("MlpPolicy", venv, seed=0, device="cpu", verbose=0, **_ppo_kwargs(tc))
    cb = make_callback(tmp_path / "fresh", tc, venv.unwrapped, seed=0)
    (tmp_path / "fresh").mkdir()
    before = {k: v.clone() for k, v in model.policy.state_dict().items()}
    model.learn(192, callback=cb)  # 3 rollouts of 64: fits after the first two
    fitted = slice(0, 32)
    lo, hi = (torch.as_tensor(b) for b in action_bounds(venv.unwrapped.world.car))
    obs = torch.as_tensor(venv.normalize_obs(cb.obs[fitted]).astype(np.float32))

    def loss():
        with torch.no_grad():
            return float(imitation_loss(mean_action(model.policy, obs), torch.as_tensor(cb.act[fitted]), lo, hi,
                                        torch.tensor([0.5, 0.15])))

    after = loss()
    model.policy.load_state_dict(before)
    assert after < 0.5 * loss(), (after, loss())


@pytest.mark.parametrize("heading", ["default", "reversed"])
def test_planner_tracks_the_road_in_either_direction(heading):
    """In a traffic world the planner's tracking is the traffic driver's pure pursuit, along or
    against the centerline: plain tracking (candidate 0) drives 2.5 s on without a contact, and
    driving on the planner's labels alone the ego laps the figure eight."""
    fw = FastWorld(n_envs=4, world="figure8", n_obstacles=0, driver="centerline", heading=heading, seed=3)
    fw.reset()
    ex = Expert(fw, horizon_s=2.5)
    assert np.all(ex.scores()[:, 0] > 3.0), ex.scores()[:, 0]  # metres in its own direction, no contact
    for _ in range(100):  # 10 s
        fw.step(ex.act())
    assert not fw.contact().any()
    assert np.all(fw.progress() > 15.0), fw.progress()


def test_committed_planner_tracks_until_a_contact_is_near_and_still_passes():
    """``Expert(commit_s=...)`` (``--expert-commit-s``): on the conflict-timed left-to-right it labels
    plain tracking until tracking would touch the crossing car within commit_s, a manoeuvre from
    there, and passes; on the paper's left-to-right, where a straight fast car passes, it never
    manoeuvres."""
    for name, conflict in (("conflict-left-to-right", True), ("left-to-right", False)):
        fw = FastWorld(n_envs=4, scenarios=[load_scenario(name)], seed=4)
        fw.reset()
        ex, probe = Expert(fw, commit_s=1.0), Expert(fw, horizon_s=2.5, track_only=True)
        first_manoeuvre, ended, ok = np.full(4, -1), np.zeros(4, bool), np.zeros(4, bool)
        tracking_hit = np.full(4, np.inf)  # tracking's contact step, seen from the first manoeuvre
        step = 0
        while not ended.all():
            track = probe.scores()[:, 0]
            a = ex.act()
            new = (ex.last_best != 0) & (first_manoeuvre < 0) & ~ended
            first_manoeuvre[new] = step
            tracking_hit[new] = track[new] - (-1000.0)
            fw.step(a)
            over = ~ended & (fw.contact() | (fw.time >= fw.time_limit - 1e-9))
            ok[over] = fw.success()[over]
            ended |= over
            step += 1
        assert ok.all(), (name, ok)
        if conflict:
            assert (first_manoeuvre > 0).all(), first_manoeuvre  # it tracked first ...
            assert (tracking_hit < 10).all(), tracking_hit  # ... until tracking hits within 1.0 s
        else:
            assert (first_manoeuvre < 0).all(), first_manoeuvre


def test_seen_only_planner_tracks_until_the_car_has_been_in_view_and_still_passes():
    """``Expert(seen_only=True)`` (``--expert-seen``): on the conflict-timed left-to-right, driving
    its own labels, it labels plain tracking at every step before its ego's scan first shows the
    car (hidden by the corner at the start), the unrestricted planner's label from then on (also
    once the car is out of view again), and passes."""
    fw = FastWorld(n_envs=4, scenarios=[load_scenario("conflict-left-to-right")], seed=4)
    fw.reset()
    ex, free = Expert(fw, seen_only=True), Expert(fw)
    ended, ok, latched = np.zeros(4, bool), np.zeros(4, bool), np.zeros(4, bool)
    hidden_steps = seen_steps = 0
    while not ended.all():
        latched |= fw.seen_by_agent(np.arange(4)).any(axis=1)
        free.last_best[:] = ex.last_best  # the same hysteresis state, so labels compare one to one
        a, b = ex.act(), free.act()
        live = ~ended
        assert np.array_equal(ex.seen[live], latched[live])
        assert (ex.last_best[~latched & live] == 0).all()
        assert np.allclose(a[latched & live], b[latched & live])
        hidden_steps += int((~latched & live).sum())
        seen_steps += int((latched & live).sum())
        fw.step(a)
        over = ~ended & (fw.contact() | (fw.time >= fw.time_limit - 1e-9))
        ok[over] = fw.success()[over]
        ended |= over
    assert ok.all() and hidden_steps > 0 and seen_steps > 0


def test_a_balanced_imitation_minibatch_is_half_teacher_labels():
    """--bc-balance: each minibatch half relabelled steps, half the others, however few of either
    are stored; uniform without it, and while one kind is missing."""
    import numpy as np

    from racecav.training.dagger import minibatches

    rng = np.random.default_rng(0)
    man = np.zeros(10_000, bool)
    man[:300] = True  # 3 % relabelled, like yield's brakes among the anchors
    batches = list(minibatches(rng, man, 2048, True, 3))
    assert len(batches) == 3 and all(len(j) == 2048 and man[j].sum() == 1024 for j in batches)
    assert 0.01 < man[next(minibatches(rng, man, 2048, False, 1))].mean() < 0.06
    assert len(next(minibatches(rng, np.zeros(50, bool), 64, True, 1))) == 64  # no relabelled step yet
