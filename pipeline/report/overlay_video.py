"""Overlay videos: every frame of every camera with the detections and the tracks drawn (MP4)."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from roomcap.capture.session import SessionLayout
from roomcap.core.errors import FormatError
from roomcap.core.fileio import atomic_path
from roomcap.core.progress import Progress
from roomcap.pipeline.report.inputs import ReportConfig, _load
from roomcap.pipeline.report.views import HAND2D_PARENTS, _Overlay, _video_paths

log = logging.getLogger(__name__)


def _bgr(k: int) -> tuple[int, int, int]:
    h = _COLORS[k % len(_COLORS)].lstrip("#")
    r, g, b = (int(h[i : i + 2], 16) for i in (0, 2, 4))
    return (b, g, r)


# the page's identity colours (report.js COLORS), the same track gets the same colour in the videos
_COLORS = (
    "#e6194b #3cb44b #4363d8 #f58231 #911eb4 #42d4f4 #f032e6 #bfef45 #fabed4 #469990 #dcbeff #9a6324 "
    "#fffac8 #800000 #aaffc3 #808000"
).split()


def draw_overlay(
    img: np.ndarray, det: np.ndarray, who: np.ndarray, proj: np.ndarray, parents, hands=None
) -> np.ndarray:
    """Draw detections (P,J,2) as thick skeletons in their track's colour (grey: no track) and the
    reprojected tracks (K,J,2) as thin white-edged skeletons with dots, on a BGR image (in place).
    ``hands``: ``(det (P,44,2), proj (K,44,2), parents (44,))`` of :data:`HAND2D`, drawn thinner."""
    import cv2

    def pt(p):
        return (int(round(p[0])), int(round(p[1])))

    s = max(1, round(max(img.shape[:2]) / 700))
    if hands is not None:
        hdet, hproj, hpar = hands
        for d, k in zip(hdet, who, strict=True):
            col = _bgr(int(k)) if k >= 0 else (170, 170, 170)
            for j, p in enumerate(hpar):
                if p >= 0 and np.isfinite(d[j]).all() and np.isfinite(d[p]).all():
                    cv2.line(img, pt(d[j]), pt(d[p]), col, s + 1, cv2.LINE_AA)
        for q in hproj:
            for j, p in enumerate(hpar):
                if p >= 0 and np.isfinite(q[j]).all() and np.isfinite(q[p]).all():
                    cv2.line(img, pt(q[j]), pt(q[p]), (255, 255, 255), 1, cv2.LINE_AA)
    for d, k in zip(det, who, strict=True):
        col = _bgr(int(k)) if k >= 0 else (170, 170, 170)
        for j, p in enumerate(parents):
            if p >= 0 and np.isfinite(d[j]).all() and np.isfinite(d[p]).all():
                cv2.line(img, pt(d[j]), pt(d[p]), col, 3 * s, cv2.LINE_AA)
    for k, q in enumerate(proj):
        col = _bgr(k)
        for j, p in enumerate(parents):
            if p >= 0 and np.isfinite(q[j]).all() and np.isfinite(q[p]).all():
                cv2.line(img, pt(q[j]), pt(q[p]), (255, 255, 255), 1 * s + 1, cv2.LINE_AA)
        for j in range(len(q)):
            if np.isfinite(q[j]).all():
                cv2.circle(img, pt(q[j]), 2 * s + 1, col, -1, cv2.LINE_AA)
                cv2.circle(img, pt(q[j]), 2 * s + 1, (255, 255, 255), 1, cv2.LINE_AA)
    return img


def write_overlay_videos(
    lay: SessionLayout,
    out_dir: Path | None = None,
    config: ReportConfig | None = None,
    progress: Progress | None = None,
) -> list[Path]:
    """Every camera's video with the detections and the reprojected tracks drawn on every frame, as
    ``report/overlay/<cam>.mp4`` (MP4V; a camera without a video: on a dark canvas of its image size).
    Returns the paths written."""
    import cv2

    cfg = config or ReportConfig()
    inp = _load(lay)
    if not inp.detections:
        raise FormatError(
            lay.keypoints_dir, None, "no detection files to draw.", "Run the keypoints stage first."
        )
    ov = _Overlay(inp, cfg)
    frames = ov.frames()
    videos = _video_paths(lay, ov.cams)
    out_dir = Path(out_dir) if out_dir is not None else lay.report_html.parent / "overlay"
    out_dir.mkdir(parents=True, exist_ok=True)
    fps = float(inp.tracks.fps) if inp.tracks is not None else 25.0
    written = []
    total = len(ov.cams) * len(frames)
    done = 0
    for cam in ov.cams:
        cap = cv2.VideoCapture(str(videos[cam])) if cam in videos else None
        if cap is not None and cap.isOpened():
            fps = float(cap.get(cv2.CAP_PROP_FPS)) or fps
            size = (int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)))
        else:
            cap = None
            size = (
                tuple(inp.rig[cam].size_wh) if inp.rig is not None and cam in inp.rig.names else (1280, 720)
            )
        path = out_dir / f"{cam}.mp4"
        with atomic_path(path, suffix=".mp4") as tmp:
            wr = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*"mp4v"), fps, size)
            if not wr.isOpened():
                raise OSError(f"cannot write {path}: OpenCV has no MP4 writer here")
            try:
                i = 0
                for start in range(0, len(frames), 256):
                    chunk = frames[start : start + 256]
                    proj = ov.project(cam, chunk)
                    hproj = ov.project(cam, chunk, hands=True) if ov.hands else None
                    for n, f in enumerate(chunk):
                        f = int(f)
                        img = None
                        if cap is not None:
                            while i < f and cap.grab():
                                i += 1
                            ok, img = cap.read() if i == f else (False, None)
                            i += 1 if ok else 0
                            if not ok:
                                img = None
                        if img is None:
                            img = np.full((size[1], size[0], 3), 24, np.uint8)
                        det = ov.detections(cam, f)
                        hands = None
                        if hproj is not None:
                            hands = (ov.detections(cam, f, hands=True), hproj[n], HAND2D_PARENTS)
                        draw_overlay(img, det, ov.match(det, proj[n]), proj[n], ov.parents, hands)
                        cv2.putText(
                            img,
                            f"{cam}  frame {f}",
                            (12, 32),
                            cv2.FONT_HERSHEY_SIMPLEX,
                            0.9,
                            (255, 255, 255),
                            2,
                        )
                        wr.write(img)
                        done += 1
                        if progress is not None:
                            progress("overlay videos", done, total)
            finally:
                wr.release()
        if cap is not None:
            cap.release()
        written.append(path)
        log.info("overlay video %s: %d frames", path, len(frames))
    return written
