"""The session report as a person sees it: headless Chromium renders it, we look at the pixels."""

from __future__ import annotations

import shutil
import subprocess

import cv2
import numpy as np
import pytest

from capture.session import SessionLayout
from keypoints.skeletons import CANONICAL
from pipeline.report import write_report
from synthetic.rigs import ring_rig
from track.trackfile import OBSERVED, TrackFile

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser") or shutil.which("google-chrome")


def make_session(root, n_people=3, T=60):
    rig = ring_rig(4, radius_m=4.0)
    lay = SessionLayout(root)
    rig.save(lay.calib_dir / "rig.toml")
    rng = np.random.default_rng(1)
    # a standing body19 template (metres, z up), walked around in circles
    tmpl = np.zeros((19, 3))
    names = CANONICAL.joint_names
    heights = {
        "nose": 1.65,
        "left_eye": 1.7,
        "right_eye": 1.7,
        "left_ear": 1.68,
        "right_ear": 1.68,
        "left_shoulder": 1.45,
        "right_shoulder": 1.45,
        "left_elbow": 1.15,
        "right_elbow": 1.15,
        "left_wrist": 0.9,
        "right_wrist": 0.9,
        "left_hip": 0.95,
        "right_hip": 0.95,
        "left_knee": 0.5,
        "right_knee": 0.5,
        "left_ankle": 0.08,
        "right_ankle": 0.08,
        "pelvis": 0.95,
        "neck": 1.5,
    }
    for j, n in enumerate(names):
        tmpl[j, 2] = heights[n]
        tmpl[j, 1] = 0.2 if n.startswith("left") else (-0.2 if n.startswith("right") else 0)
    xyz = np.full((T, n_people, 19, 3), np.nan)
    for k in range(n_people):
        for t in range(T):
            a = 2 * np.pi * (t / T + k / n_people)
            xyz[t, k] = tmpl + [1.5 * np.cos(a), 1.5 * np.sin(a), 0]
    xyz[: T // 3, -1] = np.nan  # the last person enters later
    tf = TrackFile(
        fps=25,
        frame_index=np.arange(T),
        t_ns=np.arange(T) * 40_000_000,
        track_id=np.arange(n_people),
        joint_names=names,
        parents=np.asarray(CANONICAL.parents),
        xyz_m=xyz,
        confidence=np.ones((T, n_people, 19)),
        std_m=rng.uniform(0.01, 0.03, (T, n_people, 19)),
        flags=np.full((T, n_people, 19), OBSERVED),
        source="test",
    )
    tf.save(lay.tracks)
    return lay


def render_in_browser(html_path, tmp_path):
    """Screenshot and DOM of the page after its scripts ran."""
    flags = [
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--disable-quic",
        "--no-first-run",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
        f"--user-data-dir={tmp_path / 'chrome'}",
        "--window-size=1500,1100",
        "--virtual-time-budget=4000",
        "--hide-scrollbars",
    ]
    url = html_path.resolve().as_uri()
    png = tmp_path / "shot.png"
    subprocess.run(
        [CHROMIUM, *flags, f"--screenshot={png}", url], check=True, capture_output=True, timeout=120
    )
    dom = subprocess.run(
        [CHROMIUM, *flags, "--dump-dom", url], check=True, capture_output=True, timeout=120, text=True
    ).stdout
    return cv2.imread(str(png)), dom


@pytest.mark.skipif(
    CHROMIUM is None, reason="headless Chromium not installed (apt-get install chromium; .ci/run does)"
)
def test_report_renders_people_without_errors(tmp_path):
    lay = make_session(tmp_path / "s1")
    path = write_report(lay, title="synthetic")
    text = path.read_text()
    assert "http://" not in text and "https://" not in text  # self-contained: nothing to fetch
    img, dom = render_in_browser(path, tmp_path)
    assert 'data-rendered="3"' in dom, "the viewer script did not finish"
    errors = dom.split('id="errors">', 1)[1].split("</div>", 1)[0]
    assert errors.strip() == "", f"page errors: {errors}"
    # the viewer: the dark canvas region; people are drawn in their colours inside it
    dark = np.all(np.abs(img.astype(int) - [28, 20, 16]) < 6, axis=-1)  # BGR of #10141c
    ys, xs = np.nonzero(dark)
    assert len(ys) > 100_000, "no viewer canvas on the page"
    viewer = img[ys.min() : ys.max(), xs.min() : xs.max()].astype(int)
    person_bgr = [(75, 25, 230), (75, 180, 60), (216, 99, 67)]  # #e6194b #3cb44b #4363d8
    hits = [int(np.all(np.abs(viewer - c) < 40, axis=-1).sum()) for c in person_bgr]
    assert min(hits) > 50, f"people not drawn in the viewer (pixels per person colour: {hits})"


def test_report_without_tracks_still_writes(tmp_path):
    lay = SessionLayout(tmp_path / "empty")
    lay.root.mkdir()
    path = write_report(lay, title="empty")
    assert "no track file" in path.read_text() or "tracks" in path.read_text()
