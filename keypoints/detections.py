"""The per-camera detections file ``<session>/keypoints/<cam>.npz`` (CONTRACTS.md).

Keys (shapes in letters: T frames, P detections per frame padded with NaN, J joints):

- ``schema`` = ``"detections/1"``
- ``camera`` the camera name used in rig.toml
- ``skeleton`` a skeleton id from :mod:`roomcap.keypoints.skeletons`
- ``frame_index (T,)`` int64, ``t_ns (T,)`` int64 timestamps (ns)
- ``xy_px (T,P,J,2)`` float32 full-image pixels, NaN = no detection
- ``score (T,P,J)`` float32 in [0, 1]
- ``boxes (T,P,5)`` float32 x0, y0, x1, y1, score; NaN rows for padding
- ``model`` model id and ``model_sha256``; optional ``image_size_wh (2,)``

Other tools and detectors write this file to feed the 3D stages; keep it plain.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from roomcap.core.errors import FormatError
from roomcap.core.fileio import errors_in, load_container, npz_str, save_npz, schema_tag
from roomcap.keypoints.skeletons import get_skeleton

SCHEMA = "detections"
VERSION = 1
_REQUIRED = (
    "schema",
    "camera",
    "skeleton",
    "frame_index",
    "t_ns",
    "xy_px",
    "score",
    "boxes",
    "model",
    "model_sha256",
)


@dataclass(frozen=True)
class Detections:
    camera: str
    skeleton: str
    frame_index: np.ndarray  # (T,) int64
    t_ns: np.ndarray  # (T,) int64
    xy_px: np.ndarray  # (T,P,J,2) float32, NaN = missing
    score: np.ndarray  # (T,P,J) float32
    boxes: np.ndarray  # (T,P,5) float32
    model: str = "unknown"
    model_sha256: str = ""
    image_size_wh: tuple[int, int] | None = None
    extra: dict[str, np.ndarray] = field(default_factory=dict, compare=False)

    def __post_init__(self) -> None:
        skel = get_skeleton(self.skeleton)
        T = len(self.frame_index)
        shapes = {
            "frame_index": (self.frame_index, (T,)),
            "t_ns": (self.t_ns, (T,)),
            "xy_px": (self.xy_px, (T, None, skel.n_joints, 2)),
            "score": (self.score, (T, None, skel.n_joints)),
            "boxes": (self.boxes, (T, None, 5)),
        }
        P = None
        for name, (arr, shape) in shapes.items():
            arr = np.asarray(arr)
            ok = arr.ndim == len(shape) and all(
                s is None or s == a for s, a in zip(shape, arr.shape, strict=False)
            )
            if ok and len(shape) > 1:
                P = arr.shape[1] if P is None else P
                ok = arr.shape[1] == P
            if not ok:
                want = tuple("P" if s is None else s for s in shape)
                raise FormatError(
                    None, name, f"camera '{self.camera}': expected shape {want}, got {arr.shape}."
                )
        object.__setattr__(self, "frame_index", np.asarray(self.frame_index, dtype=np.int64))
        object.__setattr__(self, "t_ns", np.asarray(self.t_ns, dtype=np.int64))
        object.__setattr__(self, "xy_px", np.asarray(self.xy_px, dtype=np.float32))
        object.__setattr__(self, "score", np.asarray(self.score, dtype=np.float32))
        object.__setattr__(self, "boxes", np.asarray(self.boxes, dtype=np.float32))

    @property
    def n_frames(self) -> int:
        return len(self.frame_index)

    @property
    def max_people(self) -> int:
        return self.xy_px.shape[1]

    def save(self, path: str | os.PathLike) -> None:
        arrays = {
            "schema": schema_tag(SCHEMA, VERSION),
            "camera": self.camera,
            "skeleton": self.skeleton,
            "frame_index": self.frame_index,
            "t_ns": self.t_ns,
            "xy_px": self.xy_px,
            "score": self.score,
            "boxes": self.boxes,
            "model": self.model,
            "model_sha256": self.model_sha256,
        }
        if self.image_size_wh is not None:
            arrays["image_size_wh"] = np.asarray(self.image_size_wh, dtype=np.int64)
        for k, v in self.extra.items():
            arrays.setdefault(k, v)
        save_npz(path, arrays)

    @classmethod
    def load(cls, path: str | os.PathLike) -> Detections:
        path = Path(path)
        data = load_container(path, SCHEMA, (VERSION,), _REQUIRED)
        known = set(_REQUIRED) | {"image_size_wh"}
        try:
            with errors_in(path):
                return cls(
                    camera=npz_str(data, "camera"),
                    skeleton=npz_str(data, "skeleton"),
                    frame_index=data["frame_index"],
                    t_ns=data["t_ns"],
                    xy_px=data["xy_px"],
                    score=data["score"],
                    boxes=data["boxes"],
                    model=npz_str(data, "model"),
                    model_sha256=npz_str(data, "model_sha256"),
                    image_size_wh=tuple(int(v) for v in data["image_size_wh"])
                    if "image_size_wh" in data
                    else None,
                    extra={k: v for k, v in data.items() if k not in known},
                )
        except KeyError as e:
            raise FormatError(path, "skeleton", str(e)) from e

    @classmethod
    def empty(cls, camera: str, skeleton: str, n_frames: int, max_people: int = 0, **kw) -> Detections:
        J = get_skeleton(skeleton).n_joints
        return cls(
            camera=camera,
            skeleton=skeleton,
            frame_index=np.arange(n_frames),
            t_ns=np.zeros(n_frames, np.int64),
            xy_px=np.full((n_frames, max_people, J, 2), np.nan),
            score=np.zeros((n_frames, max_people, J)),
            boxes=np.full((n_frames, max_people, 5), np.nan),
            **kw,
        )
