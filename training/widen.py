"""Start a wider MLP from a trained one with the same function (Net2WiderNet, Chen et al. 2016).

A 2 x 64 policy loaded into a 2 x W model (``--hidden W``): every new hidden unit copies the
incoming weights of an existing unit, and the outgoing weight of each original unit is split
between it and its copies, so the wider network computes exactly what the narrow one did. The
split is random per outgoing connection (fractions that sum to 1), not halves: with equal halves
a unit and its copy get the same gradients and stay one unit forever.

gSDE's noise weights (``log_std`` of shape (hidden, actions)) follow the last hidden layer: a unit
present c times draws c independent noises on the same activation, so each copy's std is divided
by sqrt(c) and the action noise keeps its variance.
"""

from __future__ import annotations

import numpy as np
import torch


def _layer_units(h: int, width: int, rng: np.random.Generator) -> np.ndarray:
    """Source unit of each of ``width`` units: the ``h`` originals, then copies of units drawn
    without replacement (round after round if ``width`` > 2 h)."""
    extra = [rng.permutation(h) for _ in range((width - h + h - 1) // h)]
    return np.concatenate([np.arange(h)] + extra)[:width]


def _split(units: np.ndarray, n_out: int, rng: np.random.Generator) -> np.ndarray:
    """(n_out, width) fractions: for each output, the fractions of a source unit's copies sum to 1."""
    r = rng.uniform(0.5, 1.5, size=(n_out, len(units)))
    total = np.zeros((n_out, units.max() + 1))
    np.add.at(total.T, units, r.T)
    return r / total[:, units]


def widen(state: dict, width: int, seed: int = 0) -> dict:
    """SB3 MlpPolicy state dict (2 hidden layers, actor and critic) with ``width`` units per hidden
    layer and the same outputs; ``state`` is left unchanged. Raises ValueError for a narrower
    width or another architecture."""
    rng = np.random.default_rng(seed)
    out = dict(state)
    for net, head in (("policy_net", "action_net"), ("value_net", "value_net")):
        p = f"mlp_extractor.{net}"
        keys = [f"{p}.0.weight", f"{p}.0.bias", f"{p}.2.weight", f"{p}.2.bias", f"{head}.weight"]
        if any(k not in state for k in keys) or f"{p}.4.weight" in state:
            raise ValueError(f"widen: expected an MLP of 2 hidden layers ({', '.join(keys)})")
        w0, b0, w1, b1, w2 = (state[k].numpy().astype(np.float64) for k in keys)
        h = w0.shape[0]
        if width < h:
            raise ValueError(f"widen: {width} units is narrower than the source's {h}")
        u0, u1 = _layer_units(h, width, rng), _layer_units(w1.shape[0], width, rng)
        w1 = w1[:, u0] * _split(u0, w1.shape[0], rng)  # inputs of layer 2: the split outgoing weights
        w2 = w2[:, u1] * _split(u1, w2.shape[0], rng)
        for k, v in zip(keys, (w0[u0], b0[u0], w1[u1], b1[u1], w2)):
            out[k] = torch.as_tensor(v, dtype=state[k].dtype)
        if net == "policy_net" and state["log_std"].dim() == 2:  # gSDE: one row per last hidden unit
            copies = np.bincount(u1)[u1]
            out["log_std"] = state["log_std"][torch.as_tensor(u1)] - 0.5 * torch.log(
                torch.as_tensor(copies, dtype=state["log_std"].dtype))[:, None]
    return out
