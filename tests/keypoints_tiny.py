"""Tiny ONNX graphs with the input/output signatures of the OpenMMLab exports (RTMPose SimCC, RTMO,
mmdeploy detectors), built with the ``onnx`` helper API, plus their model descriptions.

Outputs are constants chosen by the test (so decoders can be checked exactly) added to 0 x the input
mean, so the graph really depends on its input. Graphs are exported with a fixed batch of 1, like the
real SDK files, to exercise the dynamic-batch rewrite.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper


def _graph(inp: str, in_shape, outputs: dict[str, np.ndarray], path: Path) -> Path:
    nodes = [
        helper.make_node("ReduceMean", [inp], ["m"], keepdims=1, axes=[1, 2, 3]),
        helper.make_node("Mul", ["m", "zero"], ["z"]),
    ]
    inits = [numpy_helper.from_array(np.zeros((), np.float32), "zero")]
    outs = []
    for name, value in outputs.items():
        value = np.asarray(value)
        c = f"c_{name}"
        inits.append(numpy_helper.from_array(value.astype(np.float32), c))
        zr = f"zr_{name}"  # reshape (N,1,1,1) -> rank of the output, keeping N
        shape = np.array([1] * value.ndim, np.int64)
        inits.append(numpy_helper.from_array(shape, f"s_{name}"))
        nodes.append(helper.make_node("Reshape", ["z", f"s_{name}"], [zr]))
        if value.dtype.kind in "iu":
            nodes.append(helper.make_node("Add", [zr, c], [f"f_{name}"]))
            nodes.append(helper.make_node("Cast", [f"f_{name}"], [name], to=TensorProto.INT64))
            outs.append(helper.make_tensor_value_info(name, TensorProto.INT64, list(value.shape)))
        else:
            nodes.append(helper.make_node("Add", [zr, c], [name]))
            outs.append(helper.make_tensor_value_info(name, TensorProto.FLOAT, list(value.shape)))
    g = helper.make_graph(
        nodes, "tiny", [helper.make_tensor_value_info(inp, TensorProto.FLOAT, list(in_shape))], outs, inits
    )
    m = helper.make_model(g, opset_imports=[helper.make_opsetid("", 17)])
    m.ir_version = 8
    onnx.checker.check_model(m)
    onnx.save(m, str(path))
    return path


def simcc_outputs(xy_px: np.ndarray, size_wh=(192, 256), ratio=2.0, peak=0.9):
    """simcc_x (1,J,W*r), simcc_y (1,J,H*r) whose arg-max decodes to xy_px (J,2) (multiples of 1/r)."""
    J = len(xy_px)
    sx = np.full((1, J, int(size_wh[0] * ratio)), 0.01, np.float32)
    sy = np.full((1, J, int(size_wh[1] * ratio)), 0.01, np.float32)
    for j, (x, y) in enumerate(xy_px):
        sx[0, j, int(round(x * ratio))] = peak
        sy[0, j, int(round(y * ratio))] = peak
    return sx, sy


def make_simcc_model(
    folder: Path,
    xy_px: np.ndarray,
    name="tiny_simcc",
    size_wh=(192, 256),
    skeleton="coco17",
    graph_size_wh=None,
) -> Path:
    sx, sy = simcc_outputs(xy_px, size_wh)
    gw, gh = graph_size_wh or size_wh
    f = _graph("input", (1, 3, gh, gw), {"simcc_x": sx, "simcc_y": sy}, folder / f"{name}.onnx")
    (folder / f"{name}.toml").write_text(f"""schema = "keypoint-model/1"
name = "{name}"
role = "pose"
file = "{f.name}"
skeleton = "{skeleton}"
[input]
name = "input"
size_wh = [{size_wh[0]}, {size_wh[1]}]
layout = "NCHW"
color = "BGR"
mean = [123.675, 116.28, 103.53]
std = [58.395, 57.12, 57.375]
crop = "affine"
box_padding = 1.25
aspect_wh = {size_wh[0] / size_wh[1]}
[decoder]
kind = "simcc"
outputs = ["simcc_x", "simcc_y"]
split_ratio = 2.0
""")
    return f


def make_dets_model(folder: Path, boxes: np.ndarray, labels: np.ndarray, name="tiny_det", size=640) -> Path:
    """mmdeploy-style detector: dets (1,N,5) x0,y0,x1,y1,score in input px, labels (1,N)."""
    f = _graph(
        "input",
        (1, 3, size, size),
        {"dets": boxes[None].astype(np.float32), "labels": np.asarray(labels, np.int64)[None]},
        folder / f"{name}.onnx",
    )
    (folder / f"{name}.toml").write_text(f"""schema = "keypoint-model/1"
name = "{name}"
role = "detector"
file = "{f.name}"
[input]
name = "input"
size_wh = [{size}, {size}]
crop = "letterbox"
pad_value = 114
[decoder]
kind = "dets"
outputs = ["dets", "labels"]
score_threshold = 0.3
""")
    return f


def make_rtmo_model(folder: Path, dets: np.ndarray, kpts: np.ndarray, name="tiny_rtmo", size=640) -> Path:
    """RTMO-style: dets (1,N,5), keypoints (1,N,17,3) in input px."""
    f = _graph(
        "input",
        (1, 3, size, size),
        {"dets": dets[None].astype(np.float32), "keypoints": kpts[None].astype(np.float32)},
        folder / f"{name}.onnx",
    )
    (folder / f"{name}.toml").write_text(f"""schema = "keypoint-model/1"
name = "{name}"
role = "onestage"
file = "{f.name}"
skeleton = "coco17"
[input]
name = "input"
size_wh = [{size}, {size}]
crop = "letterbox"
pad_value = 114
[decoder]
kind = "rtmo"
outputs = ["dets", "keypoints"]
score_threshold = 0.5
""")
    return f
