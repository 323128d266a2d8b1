"""Policy files for the training world's traffic driver ("policy:PATH").

The format and the numpy inference live in :mod:`racecav.services.policy.model`; this module is
the name the env's ``make_traffic_driver`` imports.
"""

from racecav.services.policy.model import NumpyPolicy, export_policy, load_policy


def load_numpy_policy(name_or_path) -> NumpyPolicy:
    """A callable ``policy(obs (B, 170)) -> actions (B, 2)`` from a shipped name or a path.

    :param name_or_path: "racing" | "default" | "reversed" | path to a ``.npz``.
    """
    return load_policy(name_or_path)


__all__ = ["NumpyPolicy", "export_policy", "load_numpy_policy", "load_policy"]
