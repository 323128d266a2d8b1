"""The shipped policy as an ONNX model (onnxruntime, onnxruntime-gpu, TensorRT on the Jetson).

:func:`build_onnx` writes the whole hot path of :mod:`racecav.services.policy.fused` as ONNX
nodes, from the shipped numpy weights (:class:`~racecav.common.policy.NumpyPolicy`), so
the model takes a Scan's ranges as they are on the bus and returns the action the car drives:

    scan (B, 170) float32, metres, +inf = no return
      -> sanitize: not (-inf < r < range_max) -> range_max; then max(r, range_min)
      -> normalise (when the policy was trained with VecNormalize): clip((r - mean) / std, +-clip)
      -> tanh(x W0 + b0) -> tanh(. W1 + b1) -> . W2 + b2 -> clip to [-1, 1]
    action (B, 2) float32: [a_T, a_delta] normalised

The JSON sidecar says all of it in data (ray layout, limits, normalisation, action meaning and
the mapping to throttle and steering angle), so a C++ or TensorRT user needs nothing else.
Opset 17; the batch dimension is dynamic. ``onnx`` is needed only to build, ``onnxruntime``
only to run (extra ``onnx`` of the package).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from racecav.common.lidar import LidarSpec
from racecav.common.policy import NumpyPolicy

OPSET = 17
INPUT, OUTPUT = "scan", "action"


def build_onnx(policy: NumpyPolicy, spec: LidarSpec, name: str = "racecav_policy"):
    """The ONNX ModelProto of ``policy`` (see the module docstring)."""
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    inits, nodes = [], []

    def const(nm: str, arr) -> str:
        inits.append(numpy_helper.from_array(np.asarray(arr, dtype=np.float32), nm))
        return nm

    def node(op: str, ins: list[str], out: str, **kw) -> str:
        nodes.append(helper.make_node(op, ins, [out], name=out, **kw))
        return out

    rmin, rmax = const("range_min", spec.range_min), const("range_max", spec.range_max)
    ninf = const("neg_inf", -np.inf)
    ok = node("And", [node("Less", [INPUT, rmax], "below_max"), node("Greater", [INPUT, ninf], "above_ninf")],
              "in_range")
    x = node("Max", [node("Where", [ok, INPUT, rmax], "no_return_to_max"), rmin], "obs")
    if policy.normalize:
        c = float(policy.obs_clip)
        x = node("Mul", [node("Sub", [x, const("obs_mean", policy.obs_mean)], "centred"),
                         const("obs_inv_std", policy.obs_inv_std)], "scaled")
        x = node("Clip", [x, const("obs_clip_lo", -c), const("obs_clip_hi", c)], "obs_normalized")
    for i in range(3):
        w, b = getattr(policy, f"w{i}"), getattr(policy, f"b{i}")
        x = node("Add", [node("MatMul", [x, const(f"w{i}", w)], f"matmul{i}"), const(f"b{i}", b)], f"linear{i}")
        if i < 2:
            x = node("Tanh", [x], f"hidden{i}")
    nodes.append(helper.make_node("Clip", [x, const("act_lo", -1.0), const("act_hi", 1.0)], [OUTPUT],
                                  name="action_clip"))
    graph = helper.make_graph(
        nodes, name,
        [helper.make_tensor_value_info(INPUT, TensorProto.FLOAT, ["batch", policy.obs_dim])],
        [helper.make_tensor_value_info(OUTPUT, TensorProto.FLOAT, ["batch", policy.act_dim])], inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)],
                              producer_name="racecav", doc_string=__doc__.splitlines()[0])
    model.ir_version = 8  # readable by onnxruntime >= 1.10 and TensorRT 8.x
    onnx.checker.check_model(model)
    return model


def sidecar(policy: NumpyPolicy, spec: LidarSpec, car, source: str) -> dict:
    """What the ONNX model expects and returns, as data (written next to model.onnx)."""
    return {
        "format": "racecav.policy.onnx", "version": 1, "source": source, "opset": OPSET,
        "input": {"name": INPUT, "shape": ["batch", policy.obs_dim], "dtype": "float32",
                  "meaning": "Scan.ranges as published on racecav/<car>/scan (metres, +inf = no return); a policy "
                             "trained on a stack takes `stack` scans `stride` scan periods apart concatenated, newest "
                             "first (restart the stack with the current scan after a gap)",
                  "stack": policy.obs_stack, "stride": policy.obs_stride,
                  "rays": {"n": spec.n_rays, "angle_min": spec.angle_min, "angle_max": spec.angle_max,
                           "angle_increment": spec.angle_increment, "order": "counter-clockwise, index 0 = rightmost",
                           "frame": "laser (REP-103: x forward, y left)"},
                  "range_min": spec.range_min, "range_max": spec.range_max},
        "sanitize": "inside the model: NaN, +-inf and r >= range_max -> range_max; r < range_min -> range_min",
        "normalization": ({"inside_model": True, "kind": "VecNormalize observations",
                           "formula": "clip((obs - mean) * inv_std, -clip, clip), inv_std = 1/sqrt(var + eps)",
                           "clip": float(policy.obs_clip), "eps": float(policy.obs_eps)}
                          if policy.normalize else None),
        "output": {"name": OUTPUT, "shape": ["batch", policy.act_dim], "dtype": "float32",
                   "clip": [-1.0, 1.0], "actions": ["a_throttle", "a_steer"],
                   "meaning": "deterministic Gaussian mean of the PPO actor, clipped to [-1, 1]"},
        "to_physical": {"throttle": "T = clip(a_throttle, 0, 1)",
                        "steering_angle_rad": f"clip({car.steer_gain} * a_steer, {car.delta_min}, {car.delta_max}), + left",
                        "brake": (f"brake (VESC brake current) when a_throttle < {policy.brake_below}"
                                  if policy.brake_below is not None else "never (a_throttle <= 0 coasts)"),
                        "car": car.name},
        "network": {"layers": [int(policy.obs_dim), int(policy.w0.shape[1]), int(policy.w1.shape[1]),
                               int(policy.act_dim)], "activation": "tanh", "n_params": policy.n_params},
        "metadata": {k: policy.metadata.get(k) for k in ("stage", "heading", "timesteps", "git_commit")
                     if k in policy.metadata},
    }


def export(name_or_path: str, out_dir: Path, car_name: str = "slash") -> tuple[Path, Path]:
    """Write ``out_dir/model.onnx`` and ``out_dir/model.json`` for a shipped policy or .npz."""
    import onnx

    from racecav.common.vehicle import load_car
    from racecav.common.policy import load_policy, resolve_policy_path

    car = load_car(car_name)
    policy = load_policy(name_or_path)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    model_path, meta_path = out_dir / "model.onnx", out_dir / "model.json"
    onnx.save(build_onnx(policy, policy.lidar), model_path)
    meta = sidecar(policy, policy.lidar, car, str(resolve_policy_path(name_or_path)))
    meta_path.write_text(json.dumps(meta, indent=2) + "\n")
    return model_path, meta_path


class OnnxPolicy:
    """onnxruntime inference of the exported model: ``policy(ranges) -> (a_T, a_delta)``.

    :param model: a path to model.onnx, or a ModelProto (built in memory from the npz).
    :param threads: intra-op threads (1: the policy is 30 kFLOPs; threads only add overhead).
    """

    def __init__(self, model, threads: int = 1):
        import onnxruntime as ort

        opts = ort.SessionOptions()
        opts.intra_op_num_threads = threads
        opts.inter_op_num_threads = 1
        data = model.SerializeToString() if hasattr(model, "SerializeToString") else str(model)
        self.session = ort.InferenceSession(data, sess_options=opts, providers=["CPUExecutionProvider"])
        self._buf = np.zeros((1, self.session.get_inputs()[0].shape[1]), np.float32)

    def batch(self, ranges: np.ndarray) -> np.ndarray:
        """Actions (B, 2) for raw ranges (B, n_rays)."""
        return self.session.run([OUTPUT], {INPUT: np.asarray(ranges, np.float32)})[0]

    def __call__(self, ranges: np.ndarray) -> tuple[float, float]:
        self._buf[0] = ranges
        a = self.session.run([OUTPUT], {INPUT: self._buf})[0][0]
        return float(a[0]), float(a[1])
