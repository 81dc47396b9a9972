"""THE track file ``<session>/track/tracks.npz`` (CONTRACTS.md): the contract with forecasting and users.

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

The skeleton is ``body19`` by default; with the triangulate option ``skeleton = "whole_body"`` (or a
skeleton TOML) ``joint_names``/``parents`` carry the longer list (feet, ...), same keys.

Beside it, ``skeleton_fit.npz`` (schema ``skeleton_fit/1``, written by ``tracks fit``; see
:mod:`roomcap.outputs.skeleton_fit`) holds one skeleton per track: constant bone lengths, per-frame joint
rotations, fit error per joint, and the sha256 of the tracks.npz it was fitted on. Exporters: TRC,
C3D, CSV, JSON, BVH (:mod:`roomcap.outputs.export`, ``tracks export``).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from roomcap.core.errors import FormatError, InputError
from roomcap.core.fileio import (
    atomic_write_text,
    check_schema,
    errors_in,
    load_container,
    npz_str,
    save_npz,
    schema_tag,
)
from roomcap.keypoints.skeletons import CANONICAL, Skeleton
from roomcap.triangulate.chunks import PartStore, parts_dir

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
    def concat(cls, parts: list[TrackFile]) -> TrackFile:
        """Consecutive chunks (each with its own tracks, ids global) joined along time."""
        if not parts:
            raise FormatError(None, None, "no track parts to join.")
        ids = np.unique(np.concatenate([p.track_id for p in parts]))
        T = sum(p.n_frames for p in parts)
        J = len(parts[0].joint_names)
        K = len(ids)
        xyz = np.full((T, K, J, 3), np.nan, np.float32)
        conf = np.zeros((T, K, J), np.float32)
        std = np.full((T, K, J), np.nan, np.float32)
        flags = np.zeros((T, K, J), np.uint8)
        t = 0
        for p in parts:
            k = np.searchsorted(ids, p.track_id)
            sl = slice(t, t + p.n_frames)
            xyz[sl, k], conf[sl, k], std[sl, k], flags[sl, k] = p.xyz_m, p.confidence, p.std_m, p.flags
            t += p.n_frames
        p0 = parts[0]
        return cls(
            fps=p0.fps,
            frame_index=np.concatenate([p.frame_index for p in parts]),
            t_ns=np.concatenate([p.t_ns for p in parts]),
            track_id=ids,
            joint_names=p0.joint_names,
            parents=p0.parents,
            xyz_m=xyz,
            confidence=conf,
            std_m=std,
            flags=flags,
            calibration_sha256=p0.calibration_sha256,
            source=p0.source,
        )

    @classmethod
    def load(cls, path: str | os.PathLike) -> TrackFile:
        """The file, or where only its parts folder exists (``<name>.parts/``: a streamed run's
        ``tracks.parts/``, the live track's ``live.parts/`` read as ``track/live.npz``) its parts joined,
        each checked against its size and sha256 (:func:`iter_parts` reads them one at a time)."""
        path = Path(path)
        if not path.exists() and parts_dir(path).is_dir():
            return cls.concat(list(iter_parts(path)))
        data = load_container(path, SCHEMA, (VERSION,), _REQUIRED)
        with errors_in(path):
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


def _has_track(p: Path) -> bool:
    """The track file or its parts folder (a streamed run's ``tracks.parts/``, the live ``live.parts/``)."""
    return p.is_file() or (parts_dir(p) / "index.json").is_file()


def resolve_track_file(path: str | os.PathLike) -> tuple[Path, str]:
    """A session folder, a track file (``tracks.npz``, ``live.npz``) or its parts folder -> (track file
    path, session name). In a session the batch track ``track/tracks.npz`` comes first, else the live
    one ``track/live.npz`` (``capture-run --live``); a one-line :class:`InputError` when there is none."""
    p = Path(path)
    if p.suffix == ".parts" and (p / "index.json").is_file():
        p = p.with_suffix(".npz")
    if p.is_dir():
        cands = (p / "track" / "tracks.npz", p / "tracks.npz", p / "roomcap" / "track" / "tracks.npz")
        for cand in (*cands, p / "track" / "live.npz"):
            if _has_track(cand):
                root = cand.parent.parent if cand.parent.name == "track" else cand.parent
                if root.name == "roomcap":
                    root = root.parent
                return cand, root.name
        raise InputError(
            f"{p} has no track file (looked for track/tracks.npz, its parts and track/live.npz). Run the "
            f"track stage first: reprocess {p} --stages triangulate,track"
        )
    if not _has_track(p):
        raise InputError(f"{p} does not exist; pass a session folder or a tracks.npz.")
    session = p.parent.parent.name if p.parent.name == "track" else p.stem
    return p, session


def iter_parts(path: str | os.PathLike):
    """Yield the track file of ``path`` chunk by chunk: its parts (checked against the index), or the
    single file as one chunk. Track ids are global, each part holds the tracks present in it."""
    path = Path(path)
    if path.exists():
        yield TrackFile.load(path)
        return
    for _, _, p in PartStore(parts_dir(path), SCHEMA).checked_parts():
        yield TrackFile.load(p)


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
    """Write one track (or all, markers suffixed ``_<id>``) as OpenSim/Pose2Sim TRC, raw (blank cells
    where a joint is unknown, the track file's joint names).

    TRC is written in metres with ``Units m``. OpenSim's axes are y up; with
    ``y_up`` the world (x, y, z) with z up becomes (x, z, -y) in the file, the
    inverse of what the Pose2Sim importer in this project applies. For a file OpenSim accepts
    (Pose2Sim marker names, gaps filled, no blank cells) use :func:`roomcap.outputs.export.write_trc`.
    """
    ks = range(tf.n_tracks) if track is None else [track_index(tf, track)]
    names, cols = [], []
    for k in ks:
        for j, n in enumerate(tf.joint_names):
            names.append(n if track is not None else f"{n}_{tf.track_id[k]}")
            xyz = tf.xyz_m[:, k, j].astype(np.float64)
            cols.append(world_to_yup(xyz) if y_up else xyz)
    T = tf.n_frames
    t0 = tf.t_ns[0] if T else 0
    time_s = (tf.t_ns - t0) / 1e9 if tf.t_ns.any() else np.arange(T) / tf.fps
    write_trc_table(path, names, np.stack(cols, 1) if cols else np.zeros((T, 0, 3)), tf.fps, time_s)


def world_to_yup(xyz: np.ndarray) -> np.ndarray:
    """(..., 3) world (x, y, z), z up -> OpenSim/BVH axes (x, z, -y), y up (a proper rotation)."""
    xyz = np.asarray(xyz, np.float64)
    return np.stack([xyz[..., 0], xyz[..., 2], -xyz[..., 1]], -1)


def yup_to_world(xyz: np.ndarray) -> np.ndarray:
    """Inverse of :func:`world_to_yup`."""
    xyz = np.asarray(xyz, np.float64)
    return np.stack([xyz[..., 0], -xyz[..., 2], xyz[..., 1]], -1)


def write_trc_table(
    path: str | os.PathLike,
    names: list[str],
    xyz: np.ndarray,
    fps: float,
    time_s: np.ndarray,
    frame_no: np.ndarray | None = None,
) -> None:
    """TRC text (PathFileType 4, metres) of ``xyz (T,M,3)`` in file axes; NaN becomes a blank cell.

    ``frame_no (T,)`` is the Frame# column (default 1..T)."""
    T = len(xyz)
    frame_no = np.arange(1, T + 1) if frame_no is None else np.asarray(frame_no)
    lines = [
        f"PathFileType\t4\t(X/Y/Z)\t{Path(path).name}",
        "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\tOrigDataStartFrame\tOrigNumFrames",
        f"{fps:g}\t{fps:g}\t{T}\t{len(names)}\tm\t{fps:g}\t{int(frame_no[0]) if T else 1}\t{T}",
        "Frame#\tTime\t" + "\t\t\t".join(names) + "\t\t",
        "\t\t" + "\t".join(f"X{i + 1}\tY{i + 1}\tZ{i + 1}" for i in range(len(names))),
        "",
    ]
    for t in range(T):
        vals = "\t".join("" if not np.isfinite(v) else f"{v:.6f}" for v in xyz[t].ravel())
        lines.append(f"{int(frame_no[t])}\t{time_s[t]:.6f}\t{vals}")
    atomic_write_text(path, "\n".join(lines) + "\n")


def read_trc(path: str | os.PathLike) -> tuple[list[str], np.ndarray, np.ndarray, np.ndarray]:
    """-> (marker names, ``xyz (T,M,3)`` in file axes with NaN for blank cells, ``time_s (T,)``,
    ``frame_no (T,)``). Reads this project's and Pose2Sim's TRC files."""
    path = Path(path)
    lines = path.read_text().splitlines()
    if len(lines) < 5 or not lines[0].startswith("PathFileType"):
        raise FormatError(path, None, "not a TRC file (no PathFileType header).")
    names = [n for n in lines[3].split("\t")[2:] if n]
    rows = [ln.split("\t") for ln in lines[5:] if ln.strip()]
    out = np.full((len(rows), len(names), 3), np.nan)
    time_s, frame_no = np.zeros(len(rows)), np.zeros(len(rows), np.int64)
    for t, r in enumerate(rows):
        frame_no[t], time_s[t] = int(float(r[0])), float(r[1])
        vals = [
            float(v) if v.strip() not in ("", "nan", "NaN") else np.nan for v in r[2 : 2 + 3 * len(names)]
        ]
        vals += [np.nan] * (3 * len(names) - len(vals))
        out[t] = np.asarray(vals).reshape(len(names), 3)
    return names, out, time_s, frame_no


def export_json(tf: TrackFile, path: str | os.PathLike, track: int | None = None) -> None:
    """Plain JSON: per track, per frame, joints as [x, y, z] or null (world metres, z up), with the
    per-joint ``confidence``, ``std_m`` (uncertainty) and ``flags`` bits. All tracks, or one ``track`` id.
    :func:`read_json` reads it back."""
    ks = range(tf.n_tracks) if track is None else [track_index(tf, track)]
    out = {
        "schema": schema_tag(SCHEMA, VERSION),
        "fps": tf.fps,
        "axes": "world metres, z up",
        "flag_bits": {"observed": 1, "interpolated": 2, "predicted": 4, "smoothed": 8},
        "joint_names": list(tf.joint_names),
        "parents": tf.parents.tolist(),
        "frame_index": tf.frame_index.tolist(),
        "t_ns": tf.t_ns.tolist(),
        "tracks": [],
    }
    for k in ks:
        xyz = tf.xyz_m[:, k]
        out["tracks"].append(
            {
                "track_id": int(tf.track_id[k]),
                "xyz_m": [
                    [None if not np.isfinite(p).all() else [round(float(v), 5) for v in p] for p in fr]
                    for fr in xyz
                ],
                "std_m": [
                    [None if not np.isfinite(s) else round(float(s), 5) for s in fr] for fr in tf.std_m[:, k]
                ],
                "confidence": [[round(float(c), 4) for c in fr] for fr in tf.confidence[:, k]],
                "flags": tf.flags[:, k].tolist(),
            }
        )
    atomic_write_text(path, json.dumps(out))


def read_json(path: str | os.PathLike) -> TrackFile:
    """The track file written by :func:`export_json` (values rounded to 0.01 mm)."""
    path = Path(path)
    try:
        d = json.loads(Path(path).read_text())
        check_schema(d.get("schema"), SCHEMA, (VERSION,), path)
        T, J = len(d["frame_index"]), len(d["joint_names"])
        K = len(d["tracks"])
        xyz = np.full((T, K, J, 3), np.nan)
        std = np.full((T, K, J), np.nan)
        conf = np.zeros((T, K, J))
        flags = np.zeros((T, K, J), np.uint8)
        for k, tr in enumerate(d["tracks"]):
            xyz[:, k] = [[p if p is not None else [np.nan] * 3 for p in fr] for fr in tr["xyz_m"]]
            std[:, k] = [[np.nan if s is None else s for s in fr] for fr in tr["std_m"]]
            if "confidence" in tr:
                conf[:, k] = tr["confidence"]
            if "flags" in tr:
                flags[:, k] = tr["flags"]
        return TrackFile(
            fps=d["fps"],
            frame_index=d["frame_index"],
            t_ns=d.get("t_ns", np.round(np.arange(T) * 1e9 / d["fps"])),
            track_id=[tr["track_id"] for tr in d["tracks"]],
            joint_names=d["joint_names"],
            parents=d["parents"],
            xyz_m=xyz,
            confidence=conf,
            std_m=std,
            flags=flags,
            source=f"json:{path.name}",
        )
    except (KeyError, TypeError, ValueError) as e:
        if isinstance(e, FormatError):
            raise
        raise FormatError(path, None, f"not a roomcap track JSON ({e}).") from None


def track_index(tf: TrackFile, track: int) -> int:
    hit = np.flatnonzero(tf.track_id == int(track))
    if not len(hit):
        raise FormatError(
            None, "track_id", f"there is no track {track}; the file has tracks {tf.track_id.tolist()}."
        )
    return int(hit[0])
