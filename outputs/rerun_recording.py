"""A session as a Rerun recording (``.rrd``) to inspect in the Rerun viewer: ``tracks view SESSION --rrd
FILE``, and ``capture-run --live --rerun FILE`` while recording. Needs ``rerun-sdk``
(``pip install 'roomcap[rerun]'``).

Entities (world frame: the calibration's, metres, z up; ``rr.ViewCoordinates.RIGHT_HAND_Z_UP``):

- ``world/cameras/<cam>``: the camera's pose (``Transform3D``: world_from_camera, i.e. the rig's
  ``cam_from_world`` inverted) and its ``Pinhole`` (K of the logged image size, RDF camera axes), static;
- ``world/cameras/<cam>/image``: the camera's frames (JPEG, width at most ``max_width_px``);
- ``world/cameras/<cam>/image/detections``: the 2D detections (``Points2D``, ``body19`` joints of every
  person, in the logged image's pixels) and their bones (``.../detections/bones``, ``LineStrips2D``);
- ``world/cameras/<cam>/image/detections/hands``: where the 2D layout has hands (``*_hands``), every
  person's 42 hand joints (``Points2D``) and ``.../hands/bones`` (the wrist to the hand root, then 4 bones
  per finger);
- ``world/tracks/<track id>``: the track's joints (``Points3D``, the track file's order without the hand
  joints: ``body19`` order for a body track, NaN = unknown) with radii = the per-joint positional std (m)
  and keypoint ids = joint index in the track file; ``.../bones`` (``LineStrips3D``, the track file's
  tree); cleared at frames where the track is absent;
- ``world/tracks/<track id>/hands``: for a track with hands, its hand joints (``Points3D``, COCO-WholeBody
  names, keypoint ids = joint index in the track file, radii the std at least 4 mm) and
  ``.../hands/bones``, at frames where a hand joint is known.

Timelines: ``frame`` (the track file's ``frame_index``) and ``time`` (seconds since the first frame's
``t_ns``). Read a file back with Rerun's own reader (``rerun.chunk.RrdReader``), as the tests do.
"""

from __future__ import annotations

import logging
import queue
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from roomcap.calibrate.camera import CameraRig
from roomcap.capture.session import SessionLayout
from roomcap.capture.sources import Recording
from roomcap.core.errors import RoomcapError
from roomcap.keypoints.detections import Detections
from roomcap.keypoints.skeletons import CANONICAL, HANDS, convert, get_skeleton
from roomcap.track.trackfile import TrackFile

log = logging.getLogger(__name__)

COLORS = [  # the report's identity colours (report.js COLORS)
    "#e6194b", "#3cb44b", "#4363d8", "#f58231", "#911eb4", "#42d4f4", "#f032e6", "#bfef45",
    "#fabed4", "#469990", "#dcbeff", "#9a6324", "#fffac8", "#800000", "#aaffc3", "#808000",
]  # fmt: skip


class RerunError(RoomcapError, RuntimeError):
    """rerun-sdk missing, or the recording cannot be written."""


def _rr() -> Any:
    try:
        import rerun as rr  # lazy: loads rerun-sdk (the rerun extra, ~500 MB)
    except ImportError:
        raise RerunError(
            "writing a Rerun recording needs the rerun-sdk package, which is not installed: "
            "pip install 'roomcap[rerun]' (or pip install rerun-sdk)."
        ) from None
    return rr


def _rgb(track_id: int) -> tuple[int, int, int]:
    h = COLORS[int(track_id) % len(COLORS)]
    return int(h[1:3], 16), int(h[3:5], 16), int(h[5:7], 16)


def _bones(xyz: np.ndarray, parents: tuple[int, ...], only=None) -> list[np.ndarray]:
    """(J,D) -> one 2-point strip per bone whose two ends are known (with ``only`` (J,) bool: the bones
    to the joints it marks)."""
    return [
        np.stack([xyz[j], xyz[p]])
        for j, p in enumerate(parents)
        if p >= 0 and (only is None or only[j]) and np.isfinite(xyz[j]).all() and np.isfinite(xyz[p]).all()
    ]


def hand_detections(xy: np.ndarray, skeleton: str) -> tuple[np.ndarray, tuple[int, ...]] | None:
    """``xy (P,J,2)`` of a 2D layout with hands -> (P,44,2) the two wrists and the 42 hand joints, and
    their parents in that array (the hand roots hang from the wrists); None for a layout without hands."""
    sk = get_skeleton(skeleton)
    if not all(n in sk.joint_names for n in HANDS):
        return None
    names = ("left_wrist", "right_wrist") + HANDS
    idx = [sk.joint_names.index(n) if n in sk.joint_names else -1 for n in names]
    out = np.asarray(xy, np.float64)[:, [max(i, 0) for i in idx]]
    out[:, [k for k, i in enumerate(idx) if i < 0]] = np.nan
    parent_names = {n: sk.joint_names[p] for n, p in zip(sk.joint_names, sk.parents, strict=True) if p >= 0}
    par = tuple(names.index(parent_names[n]) if n in HANDS else -1 for n in names)
    return out, par


class RerunWriter:
    """Logs a rig, frames, detections and tracks to ``path`` (an ``.rrd`` file written as it goes)."""

    def __init__(
        self, path: str | Path, rig: CameraRig | None, name: str = "roomcap", max_width_px: int = 540
    ):
        rr = _rr()
        self.rr = rr
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.rec = rr.RecordingStream("roomcap", recording_id=name)
        self.rec.save(str(self.path))
        self.rig = rig
        self.max_w = int(max_width_px)
        self.scale: dict[str, float] = {}
        self.t0_ns: int | None = None
        self.present: set[int] = set()
        self.parents = tuple(int(p) for p in CANONICAL.parents)
        self.rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        if rig is not None:
            for cam in rig.cameras:
                w, h = cam.size_wh
                s = min(1.0, self.max_w / w)
                self.scale[cam.name] = s
                K = np.asarray(cam.K, np.float64).copy()
                K[:2] *= s
                R = np.asarray(cam.R, np.float64)
                self.rec.log(
                    f"world/cameras/{cam.name}",
                    rr.Transform3D(translation=np.asarray(cam.center, np.float64), mat3x3=R.T),
                    static=True,
                )
                self.rec.log(
                    f"world/cameras/{cam.name}/image",
                    rr.Pinhole(
                        image_from_camera=K,
                        resolution=[round(w * s), round(h * s)],
                        camera_xyz=rr.ViewCoordinates.RDF,
                        image_plane_distance=0.4,
                    ),
                    static=True,
                )

    def set_time(self, frame_index: int, t_ns: int) -> None:
        if self.t0_ns is None:
            self.t0_ns = int(t_ns)
        self.rec.set_time("frame", sequence=int(frame_index))
        self.rec.set_time("time", duration=(int(t_ns) - self.t0_ns) / 1e9)

    def image(self, cam: str, img: np.ndarray, quality: int = 80) -> None:
        s = self.scale.get(cam) or min(1.0, self.max_w / img.shape[1])
        self.scale.setdefault(cam, s)
        if s < 1.0:
            img = cv2.resize(
                img, (round(img.shape[1] * s), round(img.shape[0] * s)), interpolation=cv2.INTER_AREA
            )
        ok, jpg = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
        if ok:
            self.rec.log(
                f"world/cameras/{cam}/image",
                self.rr.EncodedImage(contents=jpg.tobytes(), media_type="image/jpeg"),
            )

    def detections(self, cam: str, xy_px: np.ndarray, hands=None) -> None:
        """xy_px (P,J,2) body19, full-size image pixels (NaN = missing); ``hands``: :func:`hand_detections`
        of the same people, or None."""
        rr = self.rr
        s = self.scale.get(cam, 1.0)
        xy = np.asarray(xy_px, np.float64).reshape(-1, CANONICAL.n_joints, 2) * s
        pts = xy.reshape(-1, 2)
        ok = np.isfinite(pts).all(-1)
        ent = f"world/cameras/{cam}/image/detections"
        self.rec.log(ent, rr.Points2D(pts[ok], radii=2.0, colors=(255, 210, 63)))
        strips = [b for p in xy for b in _bones(p, self.parents)]
        self.rec.log(f"{ent}/bones", rr.LineStrips2D(strips, colors=(255, 210, 63), radii=1.0))
        if hands is not None:
            hxy, hpar = hands
            hxy = np.asarray(hxy, np.float64) * s
            hp = hxy[:, 2:].reshape(-1, 2)
            ok = np.isfinite(hp).all(-1)
            self.rec.log(f"{ent}/hands", rr.Points2D(hp[ok], radii=1.0, colors=(63, 210, 255)))
            hs = [b for p in hxy for b in _bones(p, hpar)]
            self.rec.log(f"{ent}/hands/bones", rr.LineStrips2D(hs, colors=(63, 210, 255), radii=0.5))

    def tracks(
        self, track_id: np.ndarray, xyz_m: np.ndarray, std_m: np.ndarray, joint_names=None, parents=None
    ) -> None:
        """One frame of tracks: track_id (K,), xyz_m (K,J,3), std_m (K,J) in the skeleton ``joint_names`` /
        ``parents`` (default body19); a track with no known joint is absent (cleared); hand joints go to
        ``.../hands``."""
        rr = self.rr
        ids = np.asarray(track_id).reshape(-1)
        xyz = np.asarray(xyz_m, np.float32).reshape(len(ids), -1, 3)
        std = np.asarray(std_m, np.float32).reshape(len(ids), -1)
        par = self.parents if parents is None else tuple(int(p) for p in parents)
        hand = np.isin(np.asarray(joint_names if joint_names is not None else CANONICAL.joint_names), HANDS)
        body = np.flatnonzero(~hand)
        now = set()
        for k, tid in enumerate(ids):
            if not np.isfinite(xyz[k]).all(-1).any():
                continue
            now.add(int(tid))
            ent = f"world/tracks/{int(tid)}"
            radii = np.where(np.isfinite(std[k]), np.maximum(std[k], 0.01), 0.01)
            self.rec.log(
                ent, rr.Points3D(xyz[k, body], radii=radii[body], colors=_rgb(tid), keypoint_ids=body)
            )
            self.rec.log(
                f"{ent}/bones", rr.LineStrips3D(_bones(xyz[k], par, ~hand), colors=_rgb(tid), radii=0.012)
            )
            if hand.any():
                hj = np.flatnonzero(hand)
                seen = np.isfinite(xyz[k, hj]).all(-1)
                if seen.any():
                    hj = hj[seen]
                    hr = np.where(np.isfinite(std[k, hj]), np.maximum(std[k, hj], 0.004), 0.004)
                    pts = rr.Points3D(xyz[k, hj], radii=hr, colors=_rgb(tid), keypoint_ids=hj)
                    self.rec.log(f"{ent}/hands", pts)
                    hb = _bones(xyz[k], par, hand)
                    self.rec.log(f"{ent}/hands/bones", rr.LineStrips3D(hb, colors=_rgb(tid), radii=0.003))
                else:
                    self.rec.log(f"{ent}/hands", rr.Clear(recursive=True))
        for tid in self.present - now:
            self.rec.log(f"world/tracks/{tid}", rr.Clear(recursive=True))
        self.present = now

    def close(self) -> None:
        self.rec.flush()
        self.rec.disconnect()


def write_session_rrd(
    session: str | Path,
    track_path: str | Path,
    out: str | Path,
    *,
    images: bool = True,
    max_width_px: int = 540,
    progress: Callable[[str, int, int], None] | None = None,
) -> dict[str, Any]:
    """The session (its rig, videos, 2D detections) and the track file ``track_path`` as a Rerun recording
    ``out``. Frames without a track row are left out. Returns counts of what was logged."""
    lay = SessionLayout(session)
    tf = TrackFile.load(track_path)
    rig = CameraRig.load(lay.rig_toml) if lay.rig_toml.exists() else None
    cams = rig.names if rig is not None else lay.detection_cameras()
    dets: dict[str, tuple[dict[int, int], np.ndarray, Any]] = {}
    for cam in cams:
        p = lay.detections(cam)
        if p.exists():
            d = Detections.load(p)
            xy = np.asarray(d.xy_px)
            hands = hand_detections(xy.reshape(-1, *xy.shape[-2:]), d.skeleton)
            if hands is not None:
                hands = (hands[0].reshape(*xy.shape[:-2], *hands[0].shape[-2:]), hands[1])
            if d.skeleton != CANONICAL.id:
                xy, _ = convert(xy, np.asarray(d.score), d.skeleton, CANONICAL)
            dets[cam] = ({int(f): t for t, f in enumerate(d.frame_index)}, xy, hands)
    videos: dict[str, tuple[Any, bool]] = {}
    if images:
        for cam in cams:
            v = lay.video(cam)
            if v.exists():
                rec = Recording(v, lay.find_frames_csv(cam))
                videos[cam] = (iter(rec.iter_frames()), rec.table is not None)
    w = RerunWriter(out, rig, name=lay.root.name, max_width_px=max_width_px)
    counts = {"frames": 0, "images": 0, "detections": 0, "tracks": int(tf.n_tracks)}
    pending: dict[str, tuple[int, int, np.ndarray | None] | None] = {c: None for c in videos}
    tol_ns = int(0.5e9 / tf.fps) if tf.fps else 0  # half a frame period
    try:
        for t in range(tf.n_frames):
            fi = int(tf.frame_index[t])
            w.set_time(fi, int(tf.t_ns[t]))
            for cam, (it, timed) in videos.items():
                # the video's frame at this row: by timestamp where the video has its frames.csv (a live
                # track's rows are frame sets, not video frames), else by frame number
                key, want = (1, int(tf.t_ns[t])) if timed else (0, fi)
                item = pending[cam]
                while item is None or item[key] < want - tol_ns * timed:
                    item = next(it, None)
                    if item is None:
                        break
                pending[cam] = item
                if item is not None and abs(item[key] - want) <= tol_ns * timed and item[2] is not None:
                    w.image(cam, item[2])
                    counts["images"] += 1
            for cam, (rows, xy, hands) in dets.items():
                r = rows.get(fi)
                if r is not None:
                    w.detections(cam, xy[r], None if hands is None else (hands[0][r], hands[1]))
                    counts["detections"] += 1
            w.tracks(tf.track_id, tf.xyz_m[t], tf.std_m[t], tf.joint_names, tf.parents)
            counts["frames"] += 1
            if progress is not None:
                progress("rerun", t + 1, tf.n_frames)
    finally:
        w.close()
    return counts


class LiveRerun:
    """``capture-run --live --rerun FILE``: the live steps logged by a thread of its own from a bounded queue
    (a full queue drops the step for the file, counted in ``dropped``); images at most ``image_hz`` per
    camera."""

    def __init__(
        self,
        path: str | Path,
        layout: SessionLayout,
        rig: CameraRig | None = None,
        image_hz: float = 5.0,
        queue_size: int = 16,
    ):
        self.writer = RerunWriter(path, rig, name=layout.root.name)
        self.q: queue.Queue[Any] = queue.Queue(maxsize=queue_size)
        self.dropped = 0
        self.logged = 0
        self.image_period_ns = int(1e9 / image_hz)
        self._last_img: dict[str, int] = {}
        self._failed = False
        self._t = threading.Thread(target=self._run, name="rerun-writer", daemon=True)
        self._t.start()

    def offer(self, step: Any) -> None:
        try:
            self.q.put_nowait(step)
        except queue.Full:
            self.dropped += 1

    def _run(self) -> None:
        while True:
            step = self.q.get()
            if step is None:
                return
            if self._failed:
                continue
            try:
                self._log(step)
            except Exception as e:  # noqa: BLE001 - the recording goes on without the file
                self._failed = True
                log.warning("rerun: %s; the .rrd file stops here (logged once, the recording goes on)", e)

    def _log(self, step: Any) -> None:
        w = self.writer
        fs = step.frameset
        w.set_time(fs.index, fs.t_ns)
        for cam, f in fs.frames.items():
            if f is None or not f.has_image:
                continue
            if f.t_ns - self._last_img.get(cam, -(1 << 62)) >= self.image_period_ns:
                self._last_img[cam] = f.t_ns
                w.image(cam, np.asarray(f.decoded()))  # a camera's JPEG decoded here (full size)
        for cam, d in (step.outputs.get("detections") or {}).items():
            xy = np.asarray(d.xy_px)
            skel = getattr(d, "skeleton", CANONICAL.id)
            hands = hand_detections(xy, skel) if len(xy) else None
            if len(xy) and skel != CANONICAL.id:
                xy, _ = convert(xy, np.asarray(d.score), skel, CANONICAL)
            if len(xy):
                w.detections(cam, xy, hands)
        est = step.outputs.get("tracks")
        if est is not None:
            names = getattr(est, "joint_names", None)
            par = getattr(est, "parents", None) if names else None
            w.tracks(est.track_id, est.xyz_m, est.std_m, names, par)
        self.logged += 1

    def close(self) -> None:
        self.q.put(None)
        self._t.join(30)
        self.writer.close()
        if self.dropped:
            log.info("rerun: %d frame sets left out of the file (its writer was behind)", self.dropped)


def add_parser(sub: Any, resolve: Callable[[str], tuple[Any, str]]) -> None:
    """``tracks view SESSION --rrd FILE`` on the ``tracks`` parser's subparsers."""
    v = sub.add_parser(
        "view",
        help="write the session as a Rerun recording (.rrd) to inspect",
        description="Write SESSION (cameras as pinholes with their frames, the 2D detections, the 3D tracks "
        "over time with their uncertainty) as a Rerun recording; open it with `rerun FILE.rrd`. Needs the "
        "rerun extra: pip install 'roomcap[rerun]'.",
    )
    v.add_argument("tracks", help="session folder (or its track file)")
    v.add_argument("--rrd", type=Path, required=True, help="the .rrd file to write")
    v.add_argument("--no-images", action="store_true", help="leave the camera frames out (a small file)")
    v.add_argument(
        "--max-width", type=int, default=540, help="frames resized to at most this width (default 540)"
    )
    v.set_defaults(func=lambda args: _view_cmd(args, resolve))


def _view_cmd(args: Any, resolve: Callable[[str], tuple[Any, str]]) -> int:
    _rr()
    path, _ = resolve(args.tracks)
    p = Path(path)
    session = p.parent.parent if p.parent.name == "track" else Path(args.tracks)
    counts = write_session_rrd(
        session, path, args.rrd, images=not args.no_images, max_width_px=args.max_width
    )
    print(
        f"wrote {args.rrd}: {counts['frames']} frames, {counts['tracks']} tracks, {counts['images']} images, "
        f"{counts['detections']} detection sets (open it with: rerun {args.rrd})"
    )
    return 0
