"""``racecav policy``: the DRL policy as a controller on the bus.

Newest Scan in (racecav/<car>/scan), one DriveCommand out per usable scan (racecav/<car>/cmd,
express, high priority), naming the scan it answers. The observation is built exactly as in
training: :func:`racecav.common.lidar.sanitize` (no return / beyond range -> range_max, closer
than range_min -> range_min), then the normalisation shipped with the weights (inside
:class:`racecav.common.policy.NumpyPolicy`), then plain-numpy inference (no torch in the
loop): all three run as one compiled kernel (:mod:`racecav.services.policy.fused`), held
equal to the numpy reference by tests. Stale, malformed and missing scans get no command and
are counted (see :mod:`racecav.services.controller`).
"""

from __future__ import annotations

import argparse
from typing import Any

from racecav.common.config import Config, apply_options
from racecav.common.lidar import sanitize
from racecav.common.messages import Scan
from racecav.common.vehicle import load_car
from racecav.services.controller import ControllerService
from racecav.common.policy import ScanStack


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--model", help="reversed | default | racing | PATH to a policy .npz (default: policy.model)")
    p.add_argument("--max-scan-age", type=float, help="seconds; older scans get no command (default: policy.max_scan_age_s)")
    p.add_argument("--backend", choices=["fused", "numpy", "onnxruntime"],
                   help="inference: fused numba kernel (default), numpy reference, or onnxruntime")
    p.add_argument("--onnx", help="onnxruntime: model.onnx from `racecav train export --onnx` "
                                  "(default: built from the weights at start)")


class PolicyService(ControllerService):
    """The policy controller.

    :param cfg: whole configuration (section ``policy``).
    :param policy: a loaded NumpyPolicy (default: ``load_policy(cfg.policy.model)``).
    """

    answer_in_callback = True  # ~6 us per scan: answered as it arrives (services/controller.py)

    def __init__(self, cfg: Config, policy=None):
        from racecav.common.policy import load_policy

        pcfg = cfg.policy
        car = load_car(pcfg.car)
        policy = policy if policy is not None else load_policy(pcfg.model)
        # the policy's view (metadata "lidar"): a scan holding it is answered (services/controller.py)
        super().__init__(cfg, "policy", car, pcfg.max_scan_age_s, view=policy.lidar)
        self.model_ref = pcfg.model
        self.policy = policy
        k = self.policy.obs_stack
        if self.policy.obs_dim != k * self.spec.n_rays:
            raise ValueError(f"policy {self.model_ref!r}: expects {self.policy.obs_dim} inputs ({k} scan(s)), "
                             f"its lidar view has {self.spec.n_rays} rays")
        # a stacked policy (metadata obs_stack > 1) sees k scans obs_stride apart, newest first, as
        # in training; a lost scan or a new episode (a stamp gap) restarts the stack
        self.stack = ScanStack(k, self.policy.obs_stride)
        # trained with a brake action (EnvConfig.brake_below): a_T below it brakes, as in training
        self.brake_below = self.policy.brake_below
        self._last = (None, 0)  # (seq, stamp_ns) of the previous scan answered
        self.backend = pcfg.backend
        if self.backend == "fused":
            from racecav.services.policy.fused import FusedPolicy

            self.fused = FusedPolicy(self.policy, self.spec)
        elif self.backend == "onnxruntime":
            from racecav.services.policy.onnx_export import OnnxPolicy, build_onnx

            self.fused = OnnxPolicy(pcfg.onnx if pcfg.onnx else build_onnx(self.policy, self.spec))
        else:  # the reference: sanitize + NumpyPolicy
            self.fused = lambda ranges: tuple(float(v) for v in self.policy(sanitize(ranges, self.spec)))

    def observe(self, scan: Scan):
        """The observation of a scan, exactly as the training env builds it (reference path)."""
        return sanitize(self.view(scan), self.spec)

    def act(self, scan: Scan) -> tuple[float, float]:
        ranges = self.view(scan)
        if self.stack.n == 1:
            return self.fused(ranges)
        seq, stamp = self._last
        if seq is not None and scan.seq == seq and self.stack.buf is not None:
            return self.fused(self.stack.current())  # the same scan again (lockstep republish)
        # a stamp that jumps, or goes back (a sim restarted, a replayed log), is another episode
        if seq is None or scan.seq != seq + 1 or not 0 < scan.stamp_ns - stamp <= 1.5 * scan.scan_time * 1e9:
            self.stack.reset()
        self._last = (scan.seq, scan.stamp_ns)
        return self.fused(self.stack(ranges))

    def info(self) -> dict[str, Any]:
        return {**super().info(), "model": self.model_ref, "backend": self.backend, "normalize": self.policy.normalize,
                "n_params": self.policy.n_params, "obs_stack": self.policy.obs_stack,
                "obs_stride": self.policy.obs_stride,
                "brake_below": self.policy.brake_below, "lidar": self.policy.metadata.get("lidar", "paper")}


OPTIONS = {"model": "model", "max_scan_age": "max_scan_age_s", "backend": "backend", "onnx": "onnx"}
"""Typed options -> policy.<field> (validated as the config is: a bad one exits 2 naming both)."""
SECTION = "policy"


def run(args: argparse.Namespace, cfg: Config) -> int:
    cfg = apply_options(cfg, SECTION, args, OPTIONS)
    try:
        svc = PolicyService(cfg)
    except ImportError as e:
        print(f"racecav policy: {e} (the onnxruntime backend needs: pip install 'racecav[onnx]')")
        return 2
    except (ValueError, FileNotFoundError) as e:
        print(f"racecav policy: {e}")
        return 2
    return svc.run()
