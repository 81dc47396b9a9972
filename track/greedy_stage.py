"""The greedy track stage (seed ch. 4) on a session folder: ``triangulate/poses3d`` -> ``track/tracks``.

``track_session_greedy(session)`` reads ``triangulate/poses3d.npz`` (or its parts) and writes
``track/tracks.npz`` (or, streamed, ``track/tracks.parts/``) with :func:`roomcap.track.greedy.track_poses` or
its streamed form :mod:`roomcap.track.greedy_chunked`.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from roomcap.capture.session import SessionLayout, require
from roomcap.core.config import as_config, config_from_dict
from roomcap.keypoints.skeletons import skeleton_from_names
from roomcap.track.greedy import (
    TrackerConfig,
    facing_joints,
    frame_times_s,
    pause_clock,
    sparse_time_warning,
    track_poses,
)
from roomcap.track.greedy_chunked import build_chunks, link_chunks
from roomcap.track.trackfile import TrackFile
from roomcap.triangulate.chunks import (
    NpzRows,
    PartStore,
    StreamConfig,
    file_stamp,
    hash_key,
    parts_dir,
    remove_output,
    split_stream_keys,
)
from roomcap.triangulate.multiview import session_chunk_s
from roomcap.triangulate.poses3d import Poses3D
from roomcap.triangulate.reconstruct import flip_index

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class GreedyTrackConfig:
    """The greedy track stage: the tracker's settings (:class:`roomcap.track.greedy.TrackerConfig`) and how
    it walks the session (:class:`roomcap.triangulate.chunks.StreamConfig`; streamed by
    :mod:`roomcap.track.greedy_chunked`, one
    tracks/1 part per chunk with global track ids, equal to the whole session's result bit for bit).
    Its chunks carry the tracks from one to the next, so they run in order in one process."""

    greedy: TrackerConfig = field(default_factory=TrackerConfig)
    stream: StreamConfig = field(default_factory=StreamConfig)

    def __post_init__(self) -> None:
        self.stream.check_in_order()

    @classmethod
    def from_dict(cls, d: dict) -> GreedyTrackConfig:
        """From ``[track.options]``: the tracker's keys flat (or under ``greedy``), ``chunk_s`` flat."""
        own, stream = split_stream_keys(d)
        tracker = own.pop("greedy") if "greedy" in own else own
        if "greedy" in d and own:
            config_from_dict(cls, own)  # names the unknown keys
        return cls(
            greedy=config_from_dict(TrackerConfig, tracker), stream=config_from_dict(StreamConfig, stream)
        )


def track_session_greedy(
    session_dir: str | os.PathLike, config: GreedyTrackConfig | dict | None = None
) -> Path:
    """The chapter-4 tracker on ``triangulate/poses3d.npz`` (or its parts); writes ``track/tracks.npz``
    (streamed: ``track/tracks.parts/``, resumable; ``TrackFile.load`` reads either)."""
    cfg = as_config(GreedyTrackConfig, config)
    lay = SessionLayout(session_dir)
    if not lay.poses3d.exists() and not parts_dir(lay.poses3d).is_dir():
        require(lay.poses3d, "triangulate/poses3d.npz", "Run the triangulate stage first.")
    cfg = replace(cfg, stream=replace(cfg.stream, chunk_s=session_chunk_s(lay, cfg.stream)))
    if cfg.stream.chunk_s > 0:
        return _track_chunked(lay, cfg)
    p = Poses3D.load(lay.poses3d)
    tf = track_poses(
        p.xyz_m.astype(np.float64),
        p.frame_index,
        p.t_ns,
        p.fps,
        p.joint_names,
        np.asarray(skeleton_from_names(p.joint_names).parents if p.parents is None else p.parents),
        confidence=p.score,
        std_m=p.std_m,
        config=cfg.greedy,
        calibration_sha256=p.calibration_sha256,
    )
    remove_output(lay.tracks)
    tf.save(lay.tracks)
    log.info("greedy tracker: %d tracks over %d frames", tf.n_tracks, tf.n_frames)
    return lay.tracks


class PosesReader:
    """Frames [a, b) of ``poses3d.npz`` or of its parts, reading only the parts a range touches."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._cache: dict[int, Poses3D] = {}
        if path.exists():
            self.whole: Poses3D | None = Poses3D.load(path)
            self.spans = [(0, self.whole.n_frames, path)]
            self.stamp: object = file_stamp(path)
            head = self.whole
        else:
            self.whole = None
            store = PartStore(parts_dir(path), "poses3d")
            self.spans = store.checked_parts()
            self.stamp = (
                store.index["key"],
                [store.index["parts"][k]["sha256"] for k in sorted(store.index["parts"])],
            )
            head = Poses3D.load(self.spans[0][2])
        self.fps, self.joint_names = head.fps, head.joint_names
        self.parents = head.parents
        self.calibration_sha256 = head.calibration_sha256
        if self.whole is not None:
            self.frame_index, self.t_ns = self.whole.frame_index, self.whole.t_ns
        else:  # the frame axis of every part (small)
            fi, tn = [], []
            for _, _, p in self.spans:
                with NpzRows(p) as r:
                    fi.append(r.full("frame_index"))
                    tn.append(r.full("t_ns"))
            self.frame_index, self.t_ns = np.concatenate(fi), np.concatenate(tn)

    def _part(self, i: int) -> Poses3D:
        if self.whole is not None:
            return self.whole
        if i not in self._cache:
            if len(self._cache) >= 3:
                self._cache.pop(next(iter(self._cache)))
            self._cache[i] = Poses3D.load(self.spans[i][2])
        return self._cache[i]

    def __call__(self, a: int, b: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        xs, cs, ss = [], [], []
        for i, (f0, f1, _) in enumerate(self.spans):
            if f1 <= a or f0 >= b:
                continue
            p = self._part(i)
            sl = slice(max(a - f0, 0), min(b, f1) - f0)
            xs.append(p.xyz_m[sl])
            cs.append(p.score[sl])
            ss.append(p.std_m[sl])
        P = max(x.shape[1] for x in xs)

        def cat(arrs, fill):
            return np.concatenate(
                [
                    np.pad(x, [(0, 0), (0, P - x.shape[1])] + [(0, 0)] * (x.ndim - 2), constant_values=fill)
                    for x in arrs
                ]
            )

        return cat(xs, np.nan), cat(cs, 0.0), cat(ss, np.nan)


def _track_chunked(lay: SessionLayout, cfg: GreedyTrackConfig) -> Path:
    """The streaming greedy tracker (:mod:`roomcap.track.greedy_chunked`), one track part per chunk."""
    read = PosesReader(lay.poses3d)
    fps = read.fps
    tcfg = cfg.greedy.at_fps(fps)
    parents = np.asarray(
        skeleton_from_names(read.joint_names).parents if read.parents is None else read.parents
    )
    flip = flip_index(read.joint_names) if tcfg.fix_mirrored else None
    t_s = frame_times_s(read.frame_index, read.t_ns, fps)
    T = len(t_s)
    warn = sparse_time_warning(
        pause_clock(t_s, tcfg.max_gap_s, fps)[1], tcfg.max_gap_s, tcfg.min_track_frames, t_s
    )
    if warn:
        log.warning("greedy tracker: %s", warn)
    step = max(int(round(cfg.stream.chunk_s * fps)), 1)
    chunks = [(a, min(a + step, T)) for a in range(0, T, step)]
    key = hash_key(["tracks", repr(cfg), read.stamp])
    if lay.tracks.exists():
        lay.tracks.unlink()
    store = PartStore(parts_dir(lay.tracks), "tracks")
    todo = set(store.open(key, chunks, {"fps": fps, "n_frames": T}))
    if todo and len(todo) < len(chunks):
        log.info(
            "greedy tracker: resuming, %d of %d chunks already done", len(chunks) - len(todo), len(chunks)
        )
    if todo:
        labels, mirrored, final = link_chunks(
            read, chunks, tcfg, fps, flip, t_s, facing_joints(read.joint_names)
        )
        for i, ch in build_chunks(read, chunks, labels, mirrored, final, tcfg, parents, flip, fps, t_s, todo):
            TrackFile(
                fps=fps,
                frame_index=read.frame_index[ch.a : ch.b],
                t_ns=read.t_ns[ch.a : ch.b],
                track_id=ch.track_id,
                joint_names=read.joint_names,
                parents=parents,
                xyz_m=ch.xyz_m,
                confidence=np.clip(ch.confidence, 0, 1),
                std_m=ch.std_m,
                flags=ch.flags,
                calibration_sha256=read.calibration_sha256,
                source="track.greedy (greedy, ch. 4; streamed)",
            ).save(store.part_path(i))
            store.commit(i)
        n_tracks = int(final.max(initial=-1)) + 1
    else:
        n_tracks = -1
    store.finish({"n_tracks": n_tracks} if n_tracks >= 0 else None)
    log.info("greedy tracker (streamed): %d chunks, %s tracks over %d frames", len(chunks), n_tracks, T)
    return lay.tracks
