"""cams.yaml: the minimal file works, bad keys and values are rejected, credentials never leak."""

from __future__ import annotations

import logging

import pytest

from roomcap.capture.config import ConfigError, load_config, parse_config, redact_url, source_kind


def _write(tmp_path, text):
    p = tmp_path / "cams.yaml"
    p.write_text(text)
    return p


def test_minimal_cams_yaml_from_the_issue(tmp_path):
    p = _write(
        tmp_path,
        """
cameras:
  - name: cam01
    source: /path/to/cam01.mp4      # also usb:0, /dev/video0, rtsp://..., oak:<mxid>, synthetic:
  - name: cam02
    source: /path/to/cam02.mp4
""",
    )
    cfg = load_config(p)
    assert cfg.names == ("cam01", "cam02")
    assert cfg.cameras[0].source == "/path/to/cam01.mp4" and cfg.cameras[0].kind == "file"
    assert cfg.recorder.segment_s == 0.5 and cfg.sync.tolerance_ns(30.0) == 16_666_667  # half a frame period


@pytest.mark.parametrize(
    "source,kind",
    [
        ("usb:0", "usb"),
        ("/dev/video0", "device"),
        ("rtsp://h/x", "rtsp"),
        ("oak:1844301041B2A0F500", "oak"),
        ("oak:", "oak"),
        ("synthetic:", "synthetic"),
        ("clip.mp4", "file"),
    ],
)
def test_source_kinds(source, kind):
    assert source_kind(source) == kind


def test_full_schema_and_defaults(tmp_path):
    p = _write(
        tmp_path,
        """
out: sessions/x
calibration: calib/rig.toml
defaults: {fps: 25, resolution: [1280, 720]}
cameras:
  - {name: a, source: "synthetic:", codec: mjpg, quality: 60}
  - {name: b, source: usb:1, fps: 30, exposure_us: 5000}
sync: {tolerance_ms: 5}
recorder: {segment_s: 1.0, min_free_mb: 10}
live: {enabled: true, stages: [keypoints], every_n: 2}
""",
    )
    cfg = load_config(p)
    assert cfg.cameras[0].fps == 25 and cfg.cameras[0].resolution == (1280, 720)
    assert cfg.cameras[1].fps == 30 and cfg.cameras[1].exposure_us == 5000
    assert cfg.sync.tolerance_ns(30) == 5_000_000
    assert cfg.live.stages == ("keypoints",) and cfg.live.every_n == 2
    assert cfg.to_dict()["cameras"][0]["codec"] == "mjpg"


@pytest.mark.parametrize(
    "text,needle",
    [
        ("cameras: [{name: a, source: 'synthetic:', colour: red}]", "valid keys"),
        ("cameras: [{name: a, source: 'synthetic:'}]\nrecordr: {}", "valid keys"),
        ("cameras: [{name: a, source: 'synthetic:'}]\nsync: {tolerance: 3}", "valid keys"),
        ("cameras: [{name: a, source: 'synthetic:'}, {name: a, source: 'synthetic:'}]", "used twice"),
        ("cameras: [{name: a, source: 'synthetic:', fps: -5}]", "outside the valid range"),
        ("cameras: [{name: a, source: 'synthetic:', fps: 0}]", "outside the valid range"),
        ("cameras: [{name: a, source: 'synthetic:', resolution: [0, 480]}]", "outside the valid range"),
        ("cameras: [{name: a, source: 'synthetic:', codec: h266}]", "Valid codecs"),
        ("cameras: [{name: a, source: 'usb:0', codec: h264}]", "only OAK"),
        ("cameras: [{name: a, source: 'usb:x'}]", "integer index"),
        ("cameras: [{name: 'a b', source: 'usb:0'}]", "valid camera name"),
        ("cameras: [{name: a}]", "missing or empty"),
        ("cameras: []", "at least one camera"),
        ("cameras: [{name: a, source: 'usb:0'}, {name: b, source: 'usb:0'}]", "opened once"),
        ("cameras: [{name: a, source: 'synthetic:', fps: 100, exposure_us: 20000}]", "longer than one frame"),
        ("live: {stages: [dance]}\ncameras: [{name: a, source: 'synthetic:'}]", "Valid stages"),
    ],
)
def test_bad_configs_are_rejected_with_the_valid_options(tmp_path, text, needle):
    with pytest.raises(ConfigError, match=needle):
        load_config(_write(tmp_path, text))


def test_credentials_never_in_repr_dict_or_logs(tmp_path, caplog):
    url = "rtsp://admin:s3cr3t@10.0.0.5:554/stream?password=hunter2"
    cfg = parse_config({"cameras": [{"name": "door", "source": url}]})
    cam = cfg.cameras[0]
    assert cam.source == url  # the real URL is kept for opening the stream
    text = repr(cfg) + repr(cam) + str(cfg.to_dict())
    assert "s3cr3t" not in text and "hunter2" not in text and "admin" not in text
    assert redact_url(url) == "rtsp://***@10.0.0.5:554/stream?password=***"
    with caplog.at_level(logging.DEBUG):
        logging.getLogger("roomcap.capture").info("cam %s", cam)
    assert "s3cr3t" not in caplog.text
