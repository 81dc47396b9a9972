"""Joining a camera's recorded segments into one playable video by stream copy (no re-encode).

The recorder writes ``raw/<cam>/seg_NNNNNN.<ext>`` (kill-safe, see ``capture.recorder``). When a
recording ends, and on ``capture-run repair``, :func:`join_camera` remuxes them with PyAV into
``raw/<cam>.mp4`` (``.avi`` for MJPEG/XVID segments, whose codecs MP4 players do not expect):

1. every packet of every segment is copied, in order, into ``raw/.<cam>.join<ext>`` with its
   timestamps shifted by the duration of the segments before it (segments all start at 0);
2. the written file is opened again and its video packets are counted; the count must equal the
   rows of ``raw/<cam>.frames.csv`` (one row per recorded frame);
3. only then is the file renamed to ``raw/<cam>.<ext>`` and the segment folder removed. On a
   mismatch (or any error) the joined file is deleted and the segments are kept: nothing is lost,
   the session stays readable in its segmented form, and the result says why.
"""

from __future__ import annotations

import logging
import os
import shutil
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path

log = logging.getLogger(__name__)

FFCONCAT = "index.ffconcat"
# segment extension -> joined container extension (the recorder's codecs, capture.segments._FOURCC)
JOINED_EXT = {".mp4": ".mp4", ".avi": ".avi", ".mkv": ".mkv", ".h264": ".mp4", ".h265": ".mp4"}


@dataclass(frozen=True)
class JoinResult:
    camera: str
    ok: bool
    video: str  # session-relative path readers should use: raw/<cam>.mp4, or raw/<cam> if not joined
    frames_csv_rows: int
    frames_in_video: int  # video packets in the joined file (-1: not counted)
    segments: int
    message: str = ""

    def to_dict(self) -> dict:
        d = {
            "joined": self.ok,
            "video": self.video,
            "frames_in_video": self.frames_in_video,
            "segments_joined": self.segments,
        }
        if self.message:
            d["join_message"] = self.message
        return d


def segment_files(cam_dir: Path) -> list[Path]:
    """The closed segments ``seg_*.<video ext>`` of a camera folder, in recording order."""
    return sorted(p for p in Path(cam_dir).glob("seg_*") if p.suffix.lower() in JOINED_EXT)


def count_video_packets(path: str | os.PathLike) -> int:
    """Number of video packets (= frames for the recorder's codecs) in a file, by demuxing, no decoding."""
    import av

    with av.open(str(path)) as c:
        if not c.streams.video:
            return 0
        return sum(1 for p in c.demux(c.streams.video[0]) if p.size > 0)


def remux(segments: list[Path], dest: Path, fps: float) -> int:
    """Copy the video packets of ``segments`` into ``dest`` (format from its extension). Returns packets.

    Timestamps: each segment's are shifted by the end time of the ones before; packets without a
    timestamp (Annex B elementary streams from an OAK encoder) get ``n / fps``.
    """
    import av

    frame_s = Fraction(1, 1) / Fraction(fps if fps and fps > 0 else 30.0).limit_denominator(1001000)
    n = 0
    offset_s = Fraction(0)
    with av.open(str(dest), "w") as out:
        ost = None
        for seg in segments:
            with av.open(str(seg)) as inp:
                if not inp.streams.video:
                    raise ValueError(f"{seg}: holds no video stream")
                ist = inp.streams.video[0]
                if ost is None:
                    ost = out.add_stream_from_template(ist)
                tb = ist.time_base or frame_s
                off = round(offset_s / tb)
                end_s = offset_s
                k = 0
                for pkt in inp.demux(ist):
                    if pkt.size == 0:  # the demuxer's flush packet
                        continue
                    if pkt.pts is None or pkt.dts is None:
                        ticks = round(k * frame_s / tb)
                        pkt.pts = pkt.dts = ticks
                    dur = pkt.duration if pkt.duration else round(frame_s / tb)
                    end_s = max(end_s, offset_s + (pkt.pts + dur) * tb)
                    pkt.pts += off
                    pkt.dts += off
                    pkt.stream = ost
                    out.mux(pkt)
                    n += 1
                    k += 1
                offset_s = end_s
    return n


def join_camera(
    raw_dir: Path, cam: str, frames_csv_rows: int, fps: float, min_free_bytes: int = 0
) -> JoinResult:
    """Join ``raw_dir/<cam>/seg_*`` into ``raw_dir/<cam>.<ext>``; see the module docstring for the steps."""
    raw_dir = Path(raw_dir)
    cam_dir = raw_dir / cam
    segs = segment_files(cam_dir)
    if not segs:
        return JoinResult(cam, False, f"raw/{cam}", frames_csv_rows, -1, 0, "no closed segments to join")

    def kept(message: str, frames_in_video: int = -1) -> JoinResult:
        """Not joined: the segments stay where they are and readers use the folder."""
        return JoinResult(cam, False, f"raw/{cam}", frames_csv_rows, frames_in_video, len(segs), message)

    exts = {s.suffix.lower() for s in segs}
    if len(exts) != 1:
        return kept(
            f"segments of mixed types {sorted(exts)}",
        )
    ext = JOINED_EXT[exts.pop()]
    final = raw_dir / f"{cam}{ext}"
    need = sum(s.stat().st_size for s in segs) + min_free_bytes
    free = shutil.disk_usage(raw_dir).free
    if free < need:
        return kept(
            f"not joined: joining needs {need / 2**20:.0f} MB free, {free / 2**20:.0f} MB are; the "
            f"segments are kept. Free space and run `capture-run repair {raw_dir.parent}`",
        )
    tmp = raw_dir / f".{cam}.join{ext}"
    try:
        import av  # noqa: F401
    except ImportError:
        return kept(
            "not joined: PyAV (package 'av') is not installed; the segments are kept",
        )
    try:
        remux(segs, tmp, fps)
        with open(tmp, "rb") as f:
            os.fsync(f.fileno())
        n = count_video_packets(tmp)
    except Exception as e:  # any codec/container/disk failure: keep the segments, say why
        tmp.unlink(missing_ok=True)
        log.error("%s: joining %d segments failed (%s); the segments are kept", cam, len(segs), e)
        return kept(
            f"not joined ({type(e).__name__}: {e}); the segments are kept",
        )
    if n != frames_csv_rows:
        tmp.unlink(missing_ok=True)
        msg = (
            f"not joined: the joined video has {n} frames but raw/{cam}.frames.csv has {frames_csv_rows} "
            "rows; the segments are kept (readers use raw/<cam>/ as it is)"
        )
        log.error("%s: %s", cam, msg)
        return kept(msg, n)
    os.replace(tmp, final)
    _fsync_dir(raw_dir)
    remove_segments(cam_dir)
    _fsync_dir(raw_dir)
    log.info("%s: joined %d segments into %s (%d frames)", cam, len(segs), final.name, n)
    return JoinResult(cam, True, f"raw/{final.name}", frames_csv_rows, n, len(segs))


def remove_segments(cam_dir: Path) -> None:
    """Delete what the recorder wrote into ``raw/<cam>/``: segments, their rows, the ffconcat index, and the
    temporary files of those writes a kill left behind (``.part_*``, ``.seg_*``, ``.index.ffconcat.*``)."""
    cam_dir = Path(cam_dir)
    leftovers = (".part_", ".seg_", f".{FFCONCAT}.")
    for p in cam_dir.iterdir():
        if p.name.startswith("seg_") or p.name == FFCONCAT or p.name.startswith(leftovers):
            p.unlink()
    try:
        cam_dir.rmdir()
    except OSError:  # something the recorder did not write is in there: leave it
        log.warning("%s: left in place (holds files the recorder did not write)", cam_dir)


def _fsync_dir(d: Path) -> None:
    try:
        fd = os.open(d, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)
