"""One redaction for every place a camera source is written or shown."""

from __future__ import annotations

import logging

import pytest

from roomcap.capture.cli import main as capture_main
from roomcap.core.fileio import load_toml
from roomcap.core.redact import redact, redact_log_records, redact_url

SECRET_URL = "rtsp://host/stream?user=admin&password=hunter2&channel=1"


@pytest.mark.parametrize(
    "url,want",
    [
        ("rtsp://admin:s3cr3t@10.0.0.5:554/stream", "rtsp://***@10.0.0.5:554/stream"),
        (SECRET_URL, "rtsp://host/stream?user=***&password=***&channel=1"),
        ("http://cam/a?pwd=1&token=2&api_key=3&auth=4&secret=5&pass=6", None),
        ("https://cam/a?Username=x&X-Amz-Signature=y&fps=30#frag", "https://cam/a?Username=***&X-Amz-Signature=***&fps=30#frag"),
        ("/dev/video0", "/dev/video0"),
        ("usb:0", "usb:0"),
    ],
)  # fmt: skip
def test_redact_url_hides_userinfo_and_secret_looking_query_values(url, want):
    got = redact_url(url)
    if want is None:
        assert got == "http://cam/a?pwd=***&token=***&api_key=***&auth=***&secret=***&pass=***"
    else:
        assert got == want


def test_redact_finds_every_url_in_free_text():
    text = f"cameras:\n  - {{name: door, source: '{SECRET_URL}'}}\n  - source: \"rtsp://u:pw@h/x\" # spare"
    out = redact(text)
    assert "hunter2" not in out and "admin" not in out and ":pw@" not in out
    assert "name: door" in out and "channel=1" in out and "# spare" in out


def test_log_records_are_redacted(caplog):
    redact_log_records()
    with caplog.at_level(logging.INFO):
        logging.getLogger("roomcap.capture.sources").info("opening %s", SECRET_URL)
    assert "hunter2" not in caplog.text and "password=***" in caplog.text


def test_session_toml_and_report_hold_no_secret(tmp_path):
    yaml = (
        "cameras:\n"
        "  - {name: cam01, source: 'synthetic:'}\n"
        "  - {name: cam02, source: 'synthetic:'}\n"
        f"# the door camera, not plugged in yet: {SECRET_URL}\n"
    )
    (tmp_path / "cams.yaml").write_text(yaml)
    out = tmp_path / "s"
    args = ["--cameras", str(tmp_path / "cams.yaml"), "--out", str(out), "--duration", "0.3", "--quiet"]
    assert capture_main(args) == 0
    text = (out / "session.toml").read_text()
    assert "hunter2" not in text and "user=admin" not in text and "password=***" in text
    # a session.toml written by an older version, with the secret in it: the report redacts it again
    from roomcap.capture.session import SessionLayout
    from roomcap.pipeline.report import collect

    raw = load_toml(out / "session.toml")
    raw["cams_yaml"] = yaml
    import tomli_w

    (out / "session.toml").write_text(tomli_w.dumps(raw))
    data = collect(SessionLayout(out), "s")
    assert "hunter2" not in str(data) and "password=***" in data["session"]["cams_yaml"]
