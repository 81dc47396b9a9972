"""The skeleton fit's file, ``skeleton_fit.npz`` beside a track file (schema ``skeleton_fit/1``): each
person's bone lengths, rest pose and per-frame joint rotations (:class:`SkeletonFit`), tied to the track
file it was fitted to by that file's sha256 (:func:`file_sha256`)."""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from roomcap.core.errors import FormatError, RoomcapError
from roomcap.core.fileio import check_schema, load_npz, npz_str, save_npz, schema_tag, sha256_file
from roomcap.keypoints.skeletons import finger_bones
from roomcap.triangulate.chunks import PartStore, parts_dir

# ----------------------------------------------------------------------------- gap filling


SCHEMA = "skeleton_fit"
VERSION = 1


class FitError(RoomcapError, ValueError):
    """A track that cannot be fitted; the message says why and what to do."""


@dataclass(frozen=True)
class SkeletonFit:
    fps: float
    frame_index: np.ndarray  # (T,)
    track_id: np.ndarray  # (K,)
    joint_names: tuple[str, ...]
    parents: np.ndarray  # (J',) the fit skeleton (fit_skeleton)
    track_joints: np.ndarray  # (J,) index of each track file joint in the fit skeleton
    bone_length_m: np.ndarray  # (K,J')
    rest_offset_m: np.ndarray  # (K,J',3)
    root_xyz_m: np.ndarray  # (T,K,3)
    rotation_xyzw: np.ndarray  # (T,K,J',4)
    fit_error_m: np.ndarray  # (T,K,J) against the track file's joints
    held: np.ndarray  # (T,K,J') bool
    tracks_sha256: str = ""
    notes: tuple[str, ...] = ()  # tracks left out of the fit, and why

    @property
    def span(self) -> np.ndarray:
        """(T,K) bool: frames the fit covers."""
        return np.isfinite(self.root_xyz_m).all(-1)

    def global_rotations(self, k: int) -> np.ndarray:
        """(T,J',3,3) world rotation of each joint's frame for track index ``k`` (identity outside spans)."""
        q = np.nan_to_num(self.rotation_xyzw[:, k], nan=0.0)
        q[~np.isfinite(self.rotation_xyzw[:, k]).all(-1)] = (0, 0, 0, 1)
        T, J = q.shape[:2]
        L = Rotation.from_quat(q.reshape(-1, 4)).as_matrix().reshape(T, J, 3, 3)
        G = np.empty_like(L)
        for j in topological_order(self.parents):
            p = self.parents[j]
            G[:, j] = L[:, j] if p < 0 else G[:, p] @ L[:, j]
        return G

    def positions(self) -> np.ndarray:
        """(T,K,J',3) fitted positions of the fit skeleton's joints (world, z up), NaN outside each span."""
        T, K, J = self.rotation_xyzw.shape[:3]
        out = np.full((T, K, J, 3), np.nan)
        for k in range(K):
            G = self.global_rotations(k)
            P = np.empty((T, J, 3))
            for j in topological_order(self.parents):
                p = self.parents[j]
                P[:, j] = self.root_xyz_m[:, k] if p < 0 else P[:, p] + G[:, p] @ self.rest_offset_m[k, j]
            out[:, k] = np.where(self.span[:, k, None, None], P, np.nan)
        return out

    def joint_positions(self) -> np.ndarray:
        """(T,K,J,3) fitted positions of the track file's joints."""
        return self.positions()[:, :, self.track_joints]

    def finger_lengths_m(self, k: int) -> dict[str, np.ndarray]:
        """Track index ``k``'s finger bone lengths, by ``<side>_<finger>`` (``left_thumb``, ...): (4,) from
        the hand root to the tip (the first is the palm bone), NaN for a hand never seen; empty for a
        skeleton without hands."""
        return {
            key: np.asarray([self.bone_length_m[k, c] for _, c in bones])
            for key, bones in finger_bones(self.joint_names).items()
        }

    def save(self, path: str | os.PathLike) -> None:
        save_npz(
            path,
            {
                "schema": schema_tag(SCHEMA, VERSION),
                "tracks_sha256": self.tracks_sha256,
                "fps": np.float64(self.fps),
                "frame_index": self.frame_index,
                "track_id": self.track_id,
                "joint_names": np.asarray(self.joint_names),
                "parents": self.parents,
                "track_joints": self.track_joints,
                "bone_length_m": self.bone_length_m.astype(np.float32),
                "rest_offset_m": self.rest_offset_m,
                "root_xyz_m": self.root_xyz_m,
                "rotation_xyzw": self.rotation_xyzw,
                "fit_error_m": self.fit_error_m.astype(np.float32),
                "held": self.held,
                "notes": np.asarray(self.notes, dtype=str),
            },
        )

    @classmethod
    def load(cls, path: str | os.PathLike, tracks_sha256: str | None = None) -> SkeletonFit:
        path = Path(path)
        d = load_npz(path, required=("schema",))
        check_schema(d["schema"], SCHEMA, (VERSION,), path)
        sha = npz_str(d, "tracks_sha256")
        if tracks_sha256 is not None and sha != tracks_sha256:
            raise FormatError(
                path,
                "tracks_sha256",
                "was fitted on another version of the track file.",
                "Refit it: tracks fit <session>.",
            )
        return cls(
            fps=float(d["fps"]),
            frame_index=d["frame_index"],
            track_id=d["track_id"],
            joint_names=tuple(d["joint_names"].tolist()),
            parents=d["parents"],
            track_joints=d["track_joints"],
            bone_length_m=d["bone_length_m"].astype(np.float64),
            rest_offset_m=d["rest_offset_m"],
            root_xyz_m=d["root_xyz_m"],
            rotation_xyzw=d["rotation_xyzw"],
            fit_error_m=d["fit_error_m"].astype(np.float64),
            held=d["held"],
            tracks_sha256=sha,
            notes=tuple(d["notes"].tolist()) if "notes" in d else (),
        )


def file_sha256(path: str | os.PathLike) -> str:
    """The sha256 of a track file; of a chunked one (``tracks.parts/``, ``live.parts/``: only the folder
    exists), the sha256 of its parts' sha256 in order (each part checked against the index)."""
    path = Path(path)
    if not path.exists() and parts_dir(path).is_dir():
        h = hashlib.sha256()
        for _, _, part in PartStore(parts_dir(path), "tracks").checked_parts():
            h.update(sha256_file(part).encode())
        return h.hexdigest()
    return hashlib.sha256(path.read_bytes()).hexdigest()


def fit_path(tracks_path: str | os.PathLike) -> Path:
    """The companion fit of a track file: ``skeleton_fit.npz`` beside ``tracks.npz``,
    ``<stem>_skeleton_fit.npz`` beside another (``live_skeleton_fit.npz`` beside the live track
    ``live.npz``), so the fits of both never collide."""
    p = Path(tracks_path)
    return p.with_name("skeleton_fit.npz" if p.stem == "tracks" else f"{p.stem}_skeleton_fit.npz")


def topological_order(parents) -> list[int]:
    parents = np.asarray(parents)
    order, seen = [], set()
    while len(order) < len(parents):
        n = len(order)
        for j, p in enumerate(parents.tolist()):
            if j not in seen and (p < 0 or p in seen):
                order.append(j)
                seen.add(j)
        if len(order) == n:
            raise FitError(f"the skeleton's parents {parents.tolist()} contain a cycle.")
    return order
