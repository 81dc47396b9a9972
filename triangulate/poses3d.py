"""The per-frame 3D poses file ``<session>/triangulate/poses3d.npz`` (no identity over time; CONTRACTS.md).

Keys (T frames, P people per frame padded with NaN, J joints of ``body19``):
``schema`` = ``"poses3d/1"``, ``fps``, ``frame_index (T,)``, ``t_ns (T,)``, ``joint_names (J,)``,
``xyz_m (T,P,J,3)`` NaN = not triangulated, ``score (T,P,J)`` mean 2D confidence of the views used,
``reproj_err_px (T,P,J)`` mean reprojection error, ``n_views (T,P,J)`` int, ``calibration_sha256``;
optional ``std_m (T,P,J)`` positional std from the triangulation covariance (NaN = unknown);
optional ``cameras (C,)`` and ``reproj_err_cam_px (T,P,J,C)`` the reprojection error in each camera, NaN
where that camera's view was not used (its mean over the cameras is ``reproj_err_px``; files written
before these keys existed load with None).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from roomcap.core.errors import FormatError
from roomcap.core.fileio import errors_in, load_container, npz_str, save_npz, schema_tag
from roomcap.triangulate.chunks import PartStore, parts_dir

SCHEMA = "poses3d"
VERSION = 1
_KEYS = (
    "schema",
    "fps",
    "frame_index",
    "t_ns",
    "joint_names",
    "xyz_m",
    "score",
    "reproj_err_px",
    "n_views",
    "calibration_sha256",
)


@dataclass(frozen=True)
class Poses3D:
    fps: float
    frame_index: np.ndarray  # (T,)
    t_ns: np.ndarray  # (T,)
    joint_names: tuple[str, ...]
    xyz_m: np.ndarray  # (T,P,J,3)
    score: np.ndarray  # (T,P,J)
    reproj_err_px: np.ndarray  # (T,P,J)
    n_views: np.ndarray  # (T,P,J)
    calibration_sha256: str = ""
    std_m: np.ndarray | None = None  # (T,P,J) optional
    parents: np.ndarray | None = None  # (J,) optional: the skeleton's tree (a custom skeleton's; -1 = root)
    cameras: tuple[str, ...] | None = None  # (C,) optional, the order of reproj_err_cam_px's last axis
    reproj_err_cam_px: np.ndarray | None = None  # (T,P,J,C) optional

    def __post_init__(self) -> None:
        T, J = len(self.frame_index), len(self.joint_names)
        P = np.shape(self.xyz_m)[1] if np.ndim(self.xyz_m) == 4 else -1
        if self.std_m is None:
            object.__setattr__(self, "std_m", np.full((T, max(P, 0), J), np.nan, np.float32))
        if (self.cameras is None) != (self.reproj_err_cam_px is None):
            raise FormatError(
                None, "cameras", "cameras and reproj_err_cam_px go together: give both or neither."
            )
        if self.cameras is not None:
            object.__setattr__(self, "cameras", tuple(str(c) for c in self.cameras))
            C = len(self.cameras)
            if np.shape(self.reproj_err_cam_px) != (T, P, J, C):
                raise FormatError(
                    None,
                    "reproj_err_cam_px",
                    f"expected shape {(T, P, J, C)}, got {np.shape(self.reproj_err_cam_px)}.",
                )
            object.__setattr__(self, "reproj_err_cam_px", np.asarray(self.reproj_err_cam_px, np.float32))
        for name, shape in {
            "t_ns": (T,),
            "xyz_m": (T, P, J, 3),
            "score": (T, P, J),
            "reproj_err_px": (T, P, J),
            "n_views": (T, P, J),
            "std_m": (T, P, J),
        }.items():
            if np.shape(getattr(self, name)) != shape:
                raise FormatError(None, name, f"expected shape {shape}, got {np.shape(getattr(self, name))}.")
        for name, dtype in {
            "frame_index": np.int64,
            "t_ns": np.int64,
            "xyz_m": np.float32,
            "score": np.float32,
            "reproj_err_px": np.float32,
            "n_views": np.int16,
            "std_m": np.float32,
        }.items():
            object.__setattr__(self, name, np.asarray(getattr(self, name), dtype=dtype))
        object.__setattr__(self, "joint_names", tuple(str(n) for n in self.joint_names))

    @property
    def n_frames(self) -> int:
        return len(self.frame_index)

    @classmethod
    def concat(cls, parts: list[Poses3D]) -> Poses3D:
        """Consecutive chunks joined along time (people slots padded to the widest chunk)."""
        if not parts:
            raise FormatError(None, None, "no poses3d parts to join.")
        P = max(p.xyz_m.shape[1] for p in parts)

        def pad(name: str, fill) -> np.ndarray:
            arrs = []
            for p in parts:
                a = getattr(p, name)
                w = [(0, 0)] * a.ndim
                w[1] = (0, P - a.shape[1])
                arrs.append(np.pad(a, w, constant_values=fill))
            return np.concatenate(arrs)

        p0 = parts[0]
        return cls(
            fps=p0.fps,
            frame_index=np.concatenate([p.frame_index for p in parts]),
            t_ns=np.concatenate([p.t_ns for p in parts]),
            joint_names=p0.joint_names,
            xyz_m=pad("xyz_m", np.nan),
            score=pad("score", 0),
            reproj_err_px=pad("reproj_err_px", np.nan),
            n_views=pad("n_views", 0),
            calibration_sha256=p0.calibration_sha256,
            std_m=pad("std_m", np.nan),
            parents=p0.parents,
            cameras=p0.cameras,
            reproj_err_cam_px=None if p0.cameras is None else pad("reproj_err_cam_px", np.nan),
        )

    def save(self, path: str | os.PathLike) -> None:
        extra = {}
        if self.cameras is not None:
            extra = {"cameras": np.asarray(self.cameras), "reproj_err_cam_px": self.reproj_err_cam_px}
        save_npz(
            path,
            {
                "schema": schema_tag(SCHEMA, VERSION),
                "fps": np.float64(self.fps),
                "frame_index": self.frame_index,
                "t_ns": self.t_ns,
                "joint_names": np.asarray(self.joint_names),
                "xyz_m": self.xyz_m,
                "score": self.score,
                "reproj_err_px": self.reproj_err_px,
                "n_views": self.n_views,
                "calibration_sha256": self.calibration_sha256,
                "std_m": self.std_m,
                **({} if self.parents is None else {"parents": np.asarray(self.parents, np.int64)}),
                **extra,
            },
        )

    @classmethod
    def load(cls, path: str | os.PathLike) -> Poses3D:
        """The file, or where only ``poses3d.parts/`` exists (a chunked run) its parts joined."""
        path = Path(path)
        if not path.exists() and parts_dir(path).is_dir():
            return cls.concat([cls.load(p) for _, _, p in PartStore(parts_dir(path), SCHEMA).checked_parts()])
        data = load_container(path, SCHEMA, (VERSION,), _KEYS)
        with errors_in(path):
            return cls(
                fps=float(data["fps"]),
                frame_index=data["frame_index"],
                t_ns=data["t_ns"],
                joint_names=tuple(data["joint_names"].tolist()),
                xyz_m=data["xyz_m"],
                score=data["score"],
                reproj_err_px=data["reproj_err_px"],
                n_views=data["n_views"],
                calibration_sha256=npz_str(data, "calibration_sha256"),
                std_m=data.get("std_m"),
                parents=data.get("parents"),
                cameras=tuple(data["cameras"].tolist()) if "cameras" in data else None,
                reproj_err_cam_px=data.get("reproj_err_cam_px") if "cameras" in data else None,
            )
