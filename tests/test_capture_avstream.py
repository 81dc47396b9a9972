"""A network stream read with PyAV (capture.avstream) recorded by stream copy. No RTSP server here: a local
H.264 file with B-frames, read through the same PyAV demuxer as a stream (``live=False``), stands in. Every
written frame's packet is the source's, byte for byte, in decode order; the rows are the frames; the group
open at the end is left out and said; a codec the segments cannot take is re-encoded and said."""

from __future__ import annotations

import numpy as np
import pytest

from roomcap.capture.config import parse_config
from roomcap.capture.recorder import Recorder
from roomcap.capture.sources import read_frames_csv

av = pytest.importorskip("av", reason="PyAV not installed")

from tests.test_capture_streamcopy import _packets, _video  # noqa: E402  (after the PyAV check)


def _record(tmp_path, src):
    from roomcap.capture.avstream import AVStreamSource

    cfg = parse_config(
        {"cameras": [{"name": "a", "source": "rtsp://camera.local/stream"}], "recorder": {"segment_s": 0.2}}
    )
    source = AVStreamSource(cfg.cameras[0], url=str(src), live=False)
    rec = Recorder(cfg, tmp_path / "S", duration_s=30, sources={"a": source}, handle_signals=False)
    return rec.run()["cameras"]["a"], source


def test_a_stream_is_recorded_by_stream_copy_whole_groups_byte_identical(tmp_path):
    src = _video(tmp_path / "h264.mp4", "libx264", opts={"bf": "2", "g": "12", "sc_threshold": "0"})
    cam, source = _record(tmp_path, src)
    assert cam["recording"].startswith("stream copy of its h264 packets") and cam["joined"], cam
    # 40 frames in groups of 12: 36 written in whole groups, the last group (4 frames) left out and said
    assert cam["frames_grabbed"] == 40 and cam["frames_written"] == 36 and cam["copy_tail_dropped"] == 4
    assert cam["segments"] > 1
    got = _packets(tmp_path / "S" / cam["video"])
    assert got == _packets(src)[: len(got)] and len(got) == 36  # decode order, byte for byte
    with av.open(str(tmp_path / "S" / cam["video"])) as c:
        frames = [f.to_ndarray(format="bgr24") for f in c.decode(video=0)]
    with av.open(str(src)) as c:
        want = [f.to_ndarray(format="bgr24") for f in c.decode(video=0)][:36]
    assert len(frames) == 36 and all(np.array_equal(a, b) for a, b in zip(frames, want, strict=True))
    rows = read_frames_csv(tmp_path / "S" / "raw" / "a.frames.csv")
    assert rows[:, 0].tolist() == list(range(36)) and rows[:, 3].tolist() == list(range(36))
    from roomcap.capture.streamcopy import STREAM_TEMPLATES

    assert source._key not in STREAM_TEMPLATES  # the writer released the stream's input


def test_a_stream_codec_the_segments_cannot_take_is_reencoded_and_said(tmp_path, capsys):
    src = _video(tmp_path / "v.mkv", "ffv1", n=10)
    cam, _ = _record(tmp_path, src)
    assert cam["recording"].startswith("re-encoded: its ffv1 video cannot be stream-copied")
    assert cam["recording"].endswith("as mp4v") and cam["frames_written"] == 10 and cam["joined"]
    from roomcap.capture.cli import main

    (tmp_path / "cams.yaml").write_text("cameras:\n  - {name: a, source: 'rtsp://camera.local/s'}\n")
    assert main(["check", "--cameras", str(tmp_path / "cams.yaml")]) == 0
    assert "the stream's packets written as they come (stream copy, PyAV)" in capsys.readouterr().out
