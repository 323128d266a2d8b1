"""Training: the gymnasium env ``racecav/Overtake-v0`` (training/env.py), its batched VecEnv
(training/vec_env.py) and the PPO training of the racing and overtaking policies."""

import gymnasium as _gym

if "racecav/Overtake-v0" not in _gym.registry:
    # The env truncates at its own time limit (settings.time_limit_s): no TimeLimit wrapper.
    _gym.register(id="racecav/Overtake-v0", entry_point="racecav.training.env:OvertakeEnv")
