"""THE track file ``<session>/track/tracks.npz`` (DESIGN.md): the contract with forecasting and users.

Keys (T frames, K tracks, J joints):

- ``schema`` = ``"tracks/1"``, ``fps`` float, ``source`` (what produced it), ``calibration_sha256``
- ``frame_index (T,)`` int64, ``t_ns (T,)`` int64
- ``track_id (K,)`` int64, ``joint_names (J,)`` str, ``parents (J,)`` int64 (-1 = root)
- ``xyz_m (T,K,J,3)`` float32 world metres, z up, NaN where unknown
- ``confidence (T,K,J)`` float32 in [0, 1]
- ``std_m (T,K,J)`` float32 per-joint positional uncertainty (particle spread or
  triangulation covariance), NaN where unknown
- ``flags (T,K,J)`` uint8 bits: OBSERVED, INTERPOLATED, PREDICTED (carried through
  occlusion), SMOOTHED
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from capture.fileio import (
    FormatError,
    atomic_write_text,
    check_schema,
    load_npz,
    npz_str,
    save_npz,
    schema_tag,
)
from keypoints.skeletons import CANONICAL, Skeleton

SCHEMA = "tracks"
VERSION = 1

OBSERVED = np.uint8(1)
INTERPOLATED = np.uint8(2)
PREDICTED = np.uint8(4)
SMOOTHED = np.uint8(8)

_REQUIRED = (
    "schema",
    "fps",
    "frame_index",
    "t_ns",
    "track_id",
    "joint_names",
    "parents",
    "xyz_m",
    "confidence",
    "std_m",
    "flags",
    "calibration_sha256",
    "source",
)


@dataclass(frozen=True)
class TrackFile:
    fps: float
    frame_index: np.ndarray  # (T,)
    t_ns: np.ndarray  # (T,)
    track_id: np.ndarray  # (K,)
    joint_names: tuple[str, ...]
    parents: np.ndarray  # (J,)
    xyz_m: np.ndarray  # (T,K,J,3)
    confidence: np.ndarray  # (T,K,J)
    std_m: np.ndarray  # (T,K,J)
    flags: np.ndarray  # (T,K,J) uint8
    calibration_sha256: str = ""
    source: str = ""

    def __post_init__(self) -> None:
        T, K, J = len(self.frame_index), len(self.track_id), len(self.joint_names)
        expect = {
            "t_ns": (T,),
            "parents": (J,),
            "xyz_m": (T, K, J, 3),
            "confidence": (T, K, J),
            "std_m": (T, K, J),
            "flags": (T, K, J),
        }
        for name, shape in expect.items():
            got = np.shape(getattr(self, name))
            if got != shape:
                raise FormatError(None, name, f"expected shape {shape} (T={T}, K={K}, J={J}), got {got}.")
        if not np.isfinite(self.fps) or self.fps <= 0:
            raise FormatError(None, "fps", f"must be a positive number, got {self.fps}.")
        cast = {
            "frame_index": np.int64,
            "t_ns": np.int64,
            "track_id": np.int64,
            "parents": np.int64,
            "xyz_m": np.float32,
            "confidence": np.float32,
            "std_m": np.float32,
            "flags": np.uint8,
        }
        for name, dtype in cast.items():
            object.__setattr__(self, name, np.asarray(getattr(self, name), dtype=dtype))
        object.__setattr__(self, "joint_names", tuple(str(n) for n in self.joint_names))
        object.__setattr__(self, "fps", float(self.fps))

    @property
    def n_frames(self) -> int:
        return len(self.frame_index)

    @property
    def n_tracks(self) -> int:
        return len(self.track_id)

    @property
    def mask(self) -> np.ndarray:
        """(T,K,J) bool: joint known."""
        return np.isfinite(self.xyz_m).all(-1)

    @classmethod
    def empty(cls, frame_index, t_ns, fps: float, skeleton: Skeleton = CANONICAL, **kw) -> TrackFile:
        T, J = len(frame_index), skeleton.n_joints
        return cls(
            fps=fps,
            frame_index=frame_index,
            t_ns=t_ns,
            track_id=np.zeros(0, np.int64),
            joint_names=skeleton.joint_names,
            parents=np.asarray(skeleton.parents),
            xyz_m=np.zeros((T, 0, J, 3)),
            confidence=np.zeros((T, 0, J)),
            std_m=np.zeros((T, 0, J)),
            flags=np.zeros((T, 0, J), np.uint8),
            **kw,
        )

    def save(self, path: str | os.PathLike) -> None:
        save_npz(
            path,
            {
                "schema": schema_tag(SCHEMA, VERSION),
                "fps": np.float64(self.fps),
                "frame_index": self.frame_index,
                "t_ns": self.t_ns,
                "track_id": self.track_id,
                "joint_names": np.asarray(self.joint_names),
                "parents": self.parents,
                "xyz_m": self.xyz_m,
                "confidence": self.confidence,
                "std_m": self.std_m,
                "flags": self.flags,
                "calibration_sha256": self.calibration_sha256,
                "source": self.source,
            },
        )

    @classmethod
    def load(cls, path: str | os.PathLike) -> TrackFile:
        path = Path(path)
        data = load_npz(path, required=("schema",))
        check_schema(data["schema"], SCHEMA, (VERSION,), path)
        load_npz_required = [k for k in _REQUIRED if k not in data]
        if load_npz_required:
            raise FormatError(
                path,
                load_npz_required[0],
                f"required keys {load_npz_required} are missing.",
                "See track/trackfile.py for the track file layout.",
            )
        try:
            return cls(
                fps=float(data["fps"]),
                frame_index=data["frame_index"],
                t_ns=data["t_ns"],
                track_id=data["track_id"],
                joint_names=tuple(data["joint_names"].tolist()),
                parents=data["parents"],
                xyz_m=data["xyz_m"],
                confidence=data["confidence"],
                std_m=data["std_m"],
                flags=data["flags"],
                calibration_sha256=npz_str(data, "calibration_sha256"),
                source=npz_str(data, "source"),
            )
        except FormatError as e:
            raise FormatError(path, e.field, str(e).split(": ", 2)[-1]) from e


def load_dense(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Dense arrays plus masks for training.

    xyz_m with NaN→0, ``joint_mask (T,K,J)``, ``track_mask (T,K)``."""
    tf = TrackFile.load(path)
    joint_mask = tf.mask
    return {
        "xyz_m": np.where(joint_mask[..., None], tf.xyz_m, 0.0).astype(np.float32),
        "joint_mask": joint_mask,
        "track_mask": joint_mask.any(-1),
        "std_m": tf.std_m,
        "confidence": tf.confidence,
        "track_id": tf.track_id,
        "frame_index": tf.frame_index,
        "t_ns": tf.t_ns,
        "fps": np.float64(tf.fps),
        "joint_names": np.asarray(tf.joint_names),
        "parents": tf.parents,
    }


def export_trc(tf: TrackFile, path: str | os.PathLike, track: int | None = None, y_up: bool = True) -> None:
    """Write one track (or all, markers suffixed ``_<id>``) as OpenSim/Pose2Sim TRC.

    TRC is written in metres with ``Units m``. OpenSim's axes are y up; with
    ``y_up`` the world (x, y, z) with z up becomes (x, z, -y) in the file, the
    inverse of what the Pose2Sim importer in this project applies.
    """
    ks = range(tf.n_tracks) if track is None else [int(np.flatnonzero(tf.track_id == track)[0])]
    names, cols = [], []
    for k in ks:
        for j, n in enumerate(tf.joint_names):
            names.append(n if track is not None else f"{n}_{tf.track_id[k]}")
            xyz = tf.xyz_m[:, k, j].astype(np.float64)
            cols.append(np.stack([xyz[:, 0], xyz[:, 2], -xyz[:, 1]], -1) if y_up else xyz)
    T = tf.n_frames
    lines = [
        f"PathFileType\t4\t(X/Y/Z)\t{Path(path).name}",
        "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\tOrigDataStartFrame\tOrigNumFrames",
        f"{tf.fps:g}\t{tf.fps:g}\t{T}\t{len(names)}\tm\t{tf.fps:g}\t1\t{T}",
        "Frame#\tTime\t" + "\t\t\t".join(names) + "\t\t",
        "\t\t" + "\t".join(f"X{i + 1}\tY{i + 1}\tZ{i + 1}" for i in range(len(names))),
        "",
    ]
    t0 = tf.t_ns[0] if T else 0
    for t in range(T):
        vals = "\t".join("" if not np.isfinite(v) else f"{v:.6f}" for c in cols for v in c[t])
        lines.append(f"{t + 1}\t{(tf.t_ns[t] - t0) / 1e9 if tf.t_ns.any() else t / tf.fps:.6f}\t{vals}")
    atomic_write_text(path, "\n".join(lines) + "\n")


def export_json(tf: TrackFile, path: str | os.PathLike) -> None:
    """Plain JSON: per track, per frame, joints as [x, y, z] or null."""
    out = {
        "schema": schema_tag(SCHEMA, VERSION),
        "fps": tf.fps,
        "joint_names": list(tf.joint_names),
        "parents": tf.parents.tolist(),
        "frame_index": tf.frame_index.tolist(),
        "tracks": [],
    }
    for k, tid in enumerate(tf.track_id):
        xyz = tf.xyz_m[:, k]
        out["tracks"].append(
            {
                "track_id": int(tid),
                "xyz_m": [
                    [None if not np.isfinite(p).all() else [round(float(v), 5) for v in p] for p in fr]
                    for fr in xyz
                ],
                "std_m": [
                    [None if not np.isfinite(s) else round(float(s), 5) for s in fr] for fr in tf.std_m[:, k]
                ],
            }
        )
    atomic_write_text(path, json.dumps(out))
