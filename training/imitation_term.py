"""PPO with an imitation term: ``racecav train overtake ... --bc-coef C`` (training/train.py).

PPO alone learns slowly which of two similar scenes needs an evasion (a crossing car that will
pass ahead of the ego, or one on a collision course): its only signal is a success or a contact
seconds later. The privileged planner of ``racecav train dagger`` (training/expert.py) knows,
and pure imitation of it (dagger.py) did not reach PPO's level on the suite (docs/training.md,
rows 13-14). Here PPO keeps its objective and the planner's labels are an auxiliary loss, the
usual way to combine the two (e.g. Rajeswaran et al. 2018, DAPG): after every PPO update,
``bc_grad_steps`` minibatches of the imitation loss of dagger.py times ``bc_coef`` go through
PPO's own optimizer (or, with ``bc_learning_rate``, an Adam of their own on the actor).

The planner costs about as much per call for 64 worlds as for one (its per-step overhead
dominates), so it labels every world of the batch at ``bc_label_steps`` random steps of each
rollout, states the policy itself reached (DAgger's on-policy labels). The newest
``dataset_max`` labels are kept with their raw observations (normalised at fit time with the
run's current statistics); the aggregate is not checkpointed. imitation.csv in the run folder
holds one row per fit: labels so far, the loss, the steering agreement with the planner on the
newest labels, and the share of labels that are a manoeuvre rather than plain tracking.

``--expert mirror`` replaces the planner by the mirror teacher of training/mirror.py, the frozen
``--init-from`` policy: its action on the mirrored scans at every step it mirrors (a world running
a ``--mirror-families`` scenario whose car is near on the ego's left), and its own action at
``bc_label_steps`` random steps of each rollout (0: none) and at every step of an
``--anchor-families`` scenario whose car is near on the ego's right. The mirrored labels pull the
crossings from the left towards the reflection of the policy's crossings from the right; the
others are meant to hold the rest where it was, beside PPO's own objective. Measured (docs/training.md,
rows 34-41): the crossings from the left pass both timings, and those from the right follow them into
the mirror, with or without either kind of anchor, a wider network (row 38), labels only where the
car is in the scan (``--mirror-seen``, rows 39-41) or a fit of its own at a tenth of the learning
rate (row 41). Row 22 fitted the same labels without PPO (pure DAgger) and lost the conflicts.
``--expert track`` labels the same steps with plain tracking of the ego's road at full throttle
instead (row 44, on the paper-timed crossings from the left): the straight pass spread to every
crossing, and the conflict-timed ones were lost. ``--expert planner --expert-seen`` restricts the
planner's labels to what the policy has seen (plain tracking until a car is in the ego's scan; the
latch is kept at every step): row 49 collapsed within 2 M samples, as rows 15 and 20 did.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from racecav.training.dagger import LOSS_SCALE, STEER_TOL, action_bounds, imitation_loss, mean_action, minibatches
from racecav.training.runs import append_csv, truncate_csv

log = logging.getLogger("racecav.train")
FIELDS = ["timesteps", "labels", "loss", "steer_agree", "manoeuvres"]


def make_callback(run_dir: Path, tc, fast, seed: int):
    """The SB3 callback that labels and fits (``fast``: the run's FastVecEnv)."""
    from stable_baselines3.common.callbacks import BaseCallback

    from racecav.training.dagger import mirror_teacher
    from racecav.training.expert import Expert
    from racecav.training.mirror import RELABELS

    mirror = tc.expert in RELABELS  # the frozen init_from policy, relabelled

    class _ImitationTerm(BaseCallback):
        def __init__(self):
            super().__init__()
            self.teacher = mirror_teacher(tc, fast) if mirror else None
            self.experts = [] if mirror else [Expert(w, tc.expert_horizon_s, commit_s=tc.expert_commit_s,
                                                     seen_only=tc.expert_seen)
                                              for w in fast.worlds]
            self.car = fast.world.car
            self.lo, self.hi = action_bounds(self.car, tc.env.brake_below)
            self.rng = np.random.default_rng(seed)
            dim, cap = fast.observation_space.shape[0], tc.dataset_max
            self.obs = np.zeros((cap, dim), np.float32)
            self.act = np.zeros((cap, 2), np.float32)
            self.man = np.zeros(cap, bool)
            self.inview = np.zeros(cap, np.float32)  # aux_seen: a car in the scan at the labelled step
            self.aux_head = self.aux_opt = None
            self.size = self.head = 0
            self.new = (0, 0)  # (start, count) of the newest labels: the agreement is measured on them
            self.label_at: set[int] = set()
            self.step_in_rollout = 0
            self.path = run_dir / "imitation.csv"
            self.opt = None  # the fit's optimizer (made at the first fit, when the model exists)

        def _on_training_start(self) -> None:
            truncate_csv(self.path, self.model.num_timesteps, FIELDS)

        def _on_rollout_start(self) -> None:
            # after the previous PPO update (the train callback checkpoints after this one)
            if self.size:
                self._fit()
            self.label_at = set(self.rng.choice(tc.n_steps, min(tc.bc_label_steps, tc.n_steps), replace=False).tolist())
            self.step_in_rollout = 0
            self.new = (self.head, 0)

        def _raw_obs(self) -> np.ndarray:
            vn = self.model.get_vec_normalize_env()
            return vn.get_original_obs() if vn is not None else self.locals["new_obs"]

        def _store(self, raw: np.ndarray, label: np.ndarray, man: np.ndarray, inview=None) -> None:
            n = len(raw)
            k = np.arange(self.head, self.head + n) % len(self.obs)
            self.obs[k], self.act[k], self.man[k] = raw, label, man
            if inview is not None:
                self.inview[k] = inview
            self.head, self.size = (self.head + n) % len(self.obs), min(self.size + n, len(self.obs))
            self.new = (self.new[0], self.new[1] + n)

        def _on_step(self) -> bool:
            # the worlds' state now is the one new_obs was scanned in (auto-resets included)
            if mirror:  # every mirrored step; every world at the anchor steps
                raw = self._raw_obs()
                label, mask = self.teacher.labels(raw)
                # as the car acts (dagger.py): a policy teacher's steering saturates beyond the range
                label = np.clip(label, self.lo, self.hi)
                keep = mask | self.teacher.anchored() | (self.step_in_rollout in self.label_at)
                # --bc-balance's halves: the teacher's labels / the anchors and yield's steering round a car
                kind = mask & ~self.teacher.steered()
                if keep.any():
                    self._store(raw[keep], label[keep], kind[keep], self._in_view(keep) if tc.aux_seen > 0 else None)
            else:
                if tc.expert_seen:  # the latch of what has been in view follows every step
                    for e in self.experts:
                        e.update_seen()
                if self.step_in_rollout in self.label_at:
                    for e in self.experts:
                        e.last_best[:] = 0  # labels at spaced steps: no hysteresis to keep
                    label = np.concatenate([e.act() for e in self.experts])
                    man = np.concatenate([e.last_best != 0 for e in self.experts])
                    self._store(self._raw_obs(), label, man)
            self.step_in_rollout += 1
            return True

        def _in_view(self, keep: np.ndarray) -> np.ndarray:
            """(keep.sum(),) 1.0 where a car returns a ray of the ego's current scan, in batch order."""
            out = []
            for w, sl in zip(fast.worlds, fast.slices):
                envs = np.flatnonzero(keep[sl])
                if envs.size:
                    out.append(w.seen_by_agent(envs).any(axis=1))
            return np.concatenate(out).astype(np.float32)

        def _fit(self) -> None:
            import torch

            p, vn = self.model.policy, self.model.get_vec_normalize_env()
            norm = (lambda x: vn.normalize_obs(x).astype(np.float32)) if vn is not None else (lambda x: x)  # noqa: E731
            lo, hi = torch.as_tensor(self.lo), torch.as_tensor(self.hi)
            scale = torch.tensor(LOSS_SCALE, dtype=torch.float32)
            start, count = self.new
            k = np.arange(start, start + count) % len(self.obs)
            with torch.no_grad():
                steer = np.clip(mean_action(p, norm(self.obs[k])).numpy()[:, 1], self.lo[1], self.hi[1])
            agree = float(np.mean(np.abs(steer - self.act[k, 1]) * self.car.steer_gain < STEER_TOL)) if count else float("nan")
            if self.opt is None:
                # PPO's Adam, or one of its own: Adam moves every weight by about its learning rate per
                # step along a consistent gradient, and the imitation's is far more consistent than PPO's
                self.opt = p.optimizer if tc.bc_learning_rate is None else torch.optim.Adam(
                    [*p.mlp_extractor.policy_net.parameters(), *p.action_net.parameters()], lr=tc.bc_learning_rate)
            if tc.aux_seen > 0 and self.aux_head is None:  # training only: never saved with the policy
                self.aux_head = torch.nn.Linear(p.action_net.in_features, 1)
                self.aux_opt = torch.optim.Adam(self.aux_head.parameters(), lr=1e-3)
            p.set_training_mode(True)
            losses, hits = [], []
            for j in minibatches(self.rng, self.man[:self.size], tc.batch_size, tc.bc_balance, tc.bc_grad_steps):
                latent = p.mlp_extractor.forward_actor(p.extract_features(torch.as_tensor(norm(self.obs[j])),
                                                                          p.pi_features_extractor))
                loss = tc.bc_coef * imitation_loss(p.action_net(latent), torch.as_tensor(self.act[j]), lo, hi, scale)
                if self.aux_head is not None:
                    logit, target = self.aux_head(latent)[:, 0], torch.as_tensor(self.inview[j])
                    loss = loss + tc.aux_seen * torch.nn.functional.binary_cross_entropy_with_logits(logit, target)
                    hits.append(float(((logit > 0).float() == target).float().mean()))
                    self.aux_opt.zero_grad()
                p.optimizer.zero_grad()
                self.opt.zero_grad()
                loss.backward()
                torch.nn.utils.clip_grad_norm_(p.parameters(), tc.max_grad_norm)
                self.opt.step()
                if self.aux_head is not None:
                    self.aux_opt.step()
                losses.append(float(loss.detach()) / tc.bc_coef)
            if hits:
                log.info("aux_seen: head accuracy %.3f on %.0f %% in-view labels", np.mean(hits), 100 * self.inview[:self.size].mean())
            p.set_training_mode(False)
            append_csv(self.path, FIELDS, {"timesteps": self.model.num_timesteps, "labels": self.size,
                                           "loss": round(float(np.mean(losses)), 5), "steer_agree": round(agree, 4),
                                           "manoeuvres": round(float(self.man[:self.size].mean()), 4)})

    return _ImitationTerm()
