"""kornia against the 2D stage's own crops: is the declared dependency worth using?

The top-down 2D models take person crops cut from each frame by an affine warp (rotated upright), then
normalised into the model's input tensor (:func:`roomcap.keypoints.crops.to_tensor`). This measures, on
one 1088x1920 frame of the Pose2Sim multi-person demo (or a synthetic frame without it) and 4 crops of
192x256 (RTMPose's input), both ways to the same float32 NCHW tensor:

* ``cv2``: :func:`cv2.warpAffine` per crop on the uint8 frame, then :func:`to_tensor` (what the stage does);
* ``kornia``: the frame as a float tensor, :func:`kornia.geometry.transform.warp_affine` on the batch and
  :func:`kornia.enhance.normalize`, on the CPU (this machine has no GPU; on a GPU the frame would be
  uploaded whole, 6 MB, where the stage uploads the crops, 0.6 MB).

    python bench/bench_keypoints_kornia.py [--repeats 50]

Ends with one line ``BENCH {json}``: ms per frame of each and their ratio, and the largest difference
between the two tensors (in the model's normalised units).
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from roomcap.keypoints.crops import crop_transform, to_tensor
from roomcap.keypoints.registry import get_spec

SHARED = Path(os.environ.get("ROOMCAP_SHARED", Path(__file__).resolve().parents[2] / "shared"))
VIDEO = SHARED / "data/pose2sim/demo-wheel-0.10.49/Demo_MultiPerson/videos/cam01.mp4"


def frame() -> np.ndarray:
    cap = cv2.VideoCapture(str(VIDEO))
    ok, img = cap.read() if VIDEO.exists() else (False, None)
    if ok:
        return img
    return np.random.default_rng(0).integers(0, 255, (1920, 1088, 3), np.uint8)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=50)
    a = ap.parse_args()
    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    import kornia

    spec = get_spec("rtmpose_m_halpe26")  # float input, normalised: the case kornia could serve
    W, H = spec.input.size_wh
    img = frame()
    h, w = img.shape[:2]
    boxes = [np.array([0.1 * w + 0.2 * i * w, 0.2 * h, 0.25 * w + 0.2 * i * w, 0.8 * h]) for i in range(4)]
    Ms = np.stack([crop_transform(b, (W, H), 1.25, 0.1 * i) for i, b in enumerate(boxes)]).astype(np.float32)
    mean = torch.tensor(spec.input.mean, dtype=torch.float32) * 1.0
    std = torch.tensor(spec.input.std, dtype=torch.float32) * 1.0

    def with_cv2() -> np.ndarray:
        crops = np.stack([cv2.warpAffine(img, M, (W, H), flags=cv2.INTER_LINEAR) for M in Ms])
        return to_tensor(crops, spec)

    def with_kornia() -> np.ndarray:
        t = torch.from_numpy(img).permute(2, 0, 1)[None].float()  # (1,3,H,W) BGR
        if spec.input.color == "RGB":
            t = t.flip(1)
        t = t.expand(len(Ms), -1, -1, -1)
        crops = kornia.geometry.transform.warp_affine(t, torch.from_numpy(Ms), (H, W), align_corners=True)
        crops = crops * spec.input.scale
        return kornia.enhance.normalize(crops, mean, std).numpy()

    out = {}
    for name, fn in (("cv2", with_cv2), ("kornia", with_kornia)):
        fn()
        t0 = time.perf_counter()
        for _ in range(a.repeats):
            x = fn()
        out[name] = {"ms_per_frame": round(1000 * (time.perf_counter() - t0) / a.repeats, 2)}
        out[name]["tensor"] = x
    diff = float(np.abs(out["cv2"].pop("tensor") - out["kornia"].pop("tensor")).max())
    ratio = out["kornia"]["ms_per_frame"] / out["cv2"]["ms_per_frame"]
    print(f"cv2.warpAffine + to_tensor: {out['cv2']['ms_per_frame']:.2f} ms per frame (4 crops {W}x{H})")
    k = out["kornia"]["ms_per_frame"]
    print(f"kornia warp_affine + normalize: {k:.2f} ms ({ratio:.1f}x), max diff {diff:.3f}")
    res = {"bench": "keypoints_kornia", "frame": list(img.shape[:2]), "crops": 4, **out}
    print("BENCH " + json.dumps({**res, "kornia_over_cv2": round(ratio, 2), "max_abs_diff": round(diff, 3)}))


if __name__ == "__main__":
    main()
