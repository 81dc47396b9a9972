"""Recording a replayed video file without re-encoding it (capture.streamcopy): the recorded video's
packets are the source's, byte for byte, and decode to the same frames; the per-frame rows and the join are
those of every recording; a codec the segments cannot take is re-encoded, and ``check`` says which."""

from __future__ import annotations

import numpy as np
import pytest

from roomcap.capture.config import parse_config
from roomcap.capture.recorder import Recorder
from roomcap.capture.sources import read_frames_csv

av = pytest.importorskip("av", reason="PyAV not installed")


def _video(path, codec, n=40, fps=30, opts=None, pix="yuv420p"):
    """A small moving test video; libx264 with B-frames and short groups of pictures (decode order differs
    from presentation order, several groups per segment)."""
    if codec not in av.codecs_available:
        pytest.skip(f"no {codec} encoder in this PyAV")
    with av.open(str(path), "w") as c:
        s = c.add_stream(codec, rate=fps)
        s.width, s.height, s.pix_fmt = 160, 120, pix
        if opts:
            s.options = opts
        for i in range(n):
            img = np.zeros((120, 160, 3), np.uint8)
            img[:, (i * 3) % 160] = 255
            img[(i * 2) % 120] = 128
            for p in s.encode(av.VideoFrame.from_ndarray(img, format="bgr24")):
                c.mux(p)
        for p in s.encode():
            c.mux(p)
    return path


def _packets(path):
    with av.open(str(path)) as c:
        return [bytes(p) for p in c.demux(c.streams.video[0]) if p.size]


def _frames(path):
    with av.open(str(path)) as c:
        return [f.to_ndarray(format="bgr24") for f in c.decode(video=0)]


def _record(tmp_path, source, duration=30.0, **cam):
    cfg = parse_config(
        {
            "cameras": [{"name": "a", "source": str(source), "realtime": False, **cam}],
            "recorder": {"segment_s": 0.2},
        }
    )
    rec = Recorder(cfg, tmp_path / "S", duration_s=duration, handle_signals=False)
    return rec.run()["cameras"]["a"]


@pytest.mark.parametrize(
    ("codec", "name", "opts", "pix"),
    [
        ("libx264", "h264.mp4", {"bf": "2", "g": "12", "sc_threshold": "0"}, "yuv420p"),
        ("mjpeg", "mjpeg.avi", None, "yuvj420p"),
    ],
)
def test_a_replayed_file_is_recorded_by_stream_copy_bit_identical(tmp_path, codec, name, opts, pix):
    src = _video(tmp_path / name, codec, opts=opts, pix=pix)
    cam = _record(tmp_path, src)
    assert cam["recording"].startswith("stream copy") and cam["joined"], cam
    assert cam["frames_written"] == cam["frames_grabbed"] == 40 and cam["segments"] > 1  # cut at keyframes
    video = tmp_path / "S" / cam["video"]
    assert _packets(video) == _packets(src)  # the same bytes, no re-encoding
    got, want = _frames(video), _frames(src)
    assert len(got) == len(want) == 40 and all(np.array_equal(a, b) for a, b in zip(got, want, strict=True))
    rows = read_frames_csv(tmp_path / "S" / "raw" / "a.frames.csv")
    assert rows[:, 0].tolist() == list(range(40)) and (np.diff(rows[:, 1]) > 0).all()
    np.testing.assert_allclose(np.diff(rows[:, 1]), 1e9 / 30, atol=2e6)  # the file's own frame times


def test_a_looping_file_is_copied_across_the_wrap_and_an_unfinished_group_is_left_out(tmp_path):
    """A looping replay starts its timestamps again at the wrap: a new segment starts there. The recording
    stops within a group of pictures: that group's frames are not written (said), every other is, and the
    joined video holds exactly the rows' packets."""
    src = _video(tmp_path / "h264.mp4", "libx264", n=30, opts={"bf": "2", "g": "12", "sc_threshold": "0"})
    cam = _record(tmp_path, src, loop=True, duration=1.5)
    assert cam["joined"], cam
    n = cam["frames_written"]
    assert n > 30 and n + cam.get("copy_tail_dropped", 0) == cam["frames_grabbed"]
    one = _packets(src)
    got = _packets(tmp_path / "S" / cam["video"])
    assert len(got) == n and got == (one * (n // 30 + 1))[:n]
    assert len(read_frames_csv(tmp_path / "S" / "raw" / "a.frames.csv")) == n


def test_a_codec_the_segments_cannot_take_is_reencoded_and_check_says_so(tmp_path, capsys):
    from roomcap.capture.cli import main

    src = _video(tmp_path / "v.mkv", "ffv1", n=10, pix="yuv420p")
    h264 = _video(tmp_path / "h.mp4", "libx264")
    h264b = _video(tmp_path / "h2.mp4", "libx264")
    (tmp_path / "cams.yaml").write_text(
        f"cameras:\n  - {{name: a, source: '{src}'}}\n  - {{name: b, source: '{h264}'}}\n"
        f"  - {{name: c, source: '{h264b}', stream_copy: false, codec: mjpg}}\n"
    )
    assert main(["check", "--cameras", str(tmp_path / "cams.yaml")]) == 0
    out = capsys.readouterr().out
    assert "recording: re-encoded: its ffv1 video cannot be stream-copied" in out and "as mp4v" in out
    assert "recording: stream copy of its h264 packets" in out
    assert "recording: re-encoded: stream_copy is false in cams.yaml as mjpg" in out
    cam = _record(tmp_path, src)
    assert (
        cam["recording"].startswith("re-encoded: its ffv1") and cam["frames_written"] == 10 and cam["joined"]
    )
