"""The session report as a person sees it: headless Chromium renders it, we look at the pixels."""

from __future__ import annotations

import json
import shutil
import subprocess

import cv2
import numpy as np
import pytest
from conftest import need_shared

from roomcap.capture.session import SessionLayout
from roomcap.keypoints.skeletons import CANONICAL
from roomcap.pipeline.report import ReportConfig, track_events, write_overlay_videos, write_report
from roomcap.synthetic.rigs import ring_rig
from roomcap.track.trackfile import OBSERVED, PREDICTED, TrackFile

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser") or shutil.which("google-chrome")
need_chromium = pytest.mark.skipif(
    CHROMIUM is None, reason="headless Chromium not installed (apt-get install chromium; .ci/run does)"
)


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


def synthetic_session(root, seconds=3.0, cams=4, people=2, seed=0):
    """A rendered synthetic session (calibration + detections, no videos), triangulated and tracked."""
    from roomcap.synthetic import render as R
    from roomcap.synthetic import rigs, world
    from roomcap.track.greedy_stage import track_session_greedy
    from roomcap.triangulate.stage import triangulate_session

    rig, room = rigs.ring_rig(cams, 3.0, seed=seed), rigs.ring_room(3.0)
    scene = world.make_scene(room, world.SceneConfig(n_people=people, duration_s=seconds, seed=seed))
    lay = world.write_session(
        scene,
        R.render(
            scene,
            rig,
            R.RenderConfig(noise_px=2.0, missed_joint_rate=0.05, false_positive_rate=0.1, seed=seed),
        ),
        rig,
        root,
    )
    triangulate_session(lay.root)
    track_session_greedy(lay.root)
    return lay


def report_data(path) -> dict:
    text = path.read_text()
    payload = text.split('<script id="data" type="application/json">', 1)[1].split("</script>", 1)[0]
    return json.loads(payload.replace("<\\/", "</"))


def render_in_browser(html_path, out_dir, height=1100, name="shot"):
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
        f"--user-data-dir={out_dir / 'chrome'}",
        f"--window-size=1500,{height}",
        "--virtual-time-budget=6000",
        "--hide-scrollbars",
    ]
    url = html_path.resolve().as_uri()
    png = out_dir / f"{name}.png"
    for _ in range(3):  # the page marks data-films once its images decoded; on a busy machine that can come
        # after the virtual-time budget, so a page caught before it is rendered again (CI saw one such)
        subprocess.run(
            [CHROMIUM, *flags, f"--screenshot={png}", url], check=True, capture_output=True, timeout=180
        )
        dom = subprocess.run(
            [CHROMIUM, *flags, "--dump-dom", url], check=True, capture_output=True, timeout=180, text=True
        ).stdout
        if 'data-films="' in dom:
            break
    return cv2.imread(str(png)), dom


def page_errors(dom: str) -> str:
    return dom.split('id="errors">', 1)[1].split("</div>", 1)[0].strip()


def film_rects(dom: str) -> dict:
    import html

    raw = dom.split('data-film-rects="', 1)[1].split('"', 1)[0]
    return json.loads(html.unescape(raw))


def dom_cell_values(dom: str, table_id: str) -> list[list[float | None]]:
    """The data-v values of a rendered table's rows (None where a cell has none)."""
    import re

    body = dom.split(f'id="{table_id}"', 1)[1].split("</table>", 1)[0]
    rows = []
    for tr in re.findall(r"<tr[^>]*>(.*?)</tr>", body, re.S):
        cells = re.findall(r"<td([^>]*)>", tr)
        if cells:
            rows.append(
                [float(m.group(1)) if (m := re.search(r'data-v="([^"]+)"', c)) else None for c in cells]
            )
    return rows


def independent_camera_figures(poses3d_path):
    """Per-camera mean / median / 90th percentile / count straight from the arrays triangulate wrote."""
    d = np.load(poses3d_path)
    err, nv, ec = d["reproj_err_px"], d["n_views"], d["reproj_err_cam_px"]
    ok = np.isfinite(err) & (nv > 0)
    out = {}
    for c, name in enumerate(d["cameras"].tolist()):
        v = ec[..., c][ok & np.isfinite(ec[..., c])].astype(np.float64)
        out[name] = (round(v.mean(), 3), round(np.median(v), 3), round(np.percentile(v, 90), 3), len(v))
    return out, round(float(err[ok].astype(np.float64).mean()), 3)


# ----------------------------------------------------------------------------- triangulate


def test_triangulate_writes_the_per_camera_errors_its_mean_is_made_of(tmp_path):
    from roomcap.triangulate.poses3d import Poses3D

    lay = synthetic_session(tmp_path / "s")
    p = Poses3D.load(lay.poses3d)
    assert p.cameras == tuple(SessionLayout(lay.root).detection_cameras())
    ec = p.reproj_err_cam_px.astype(np.float64)
    ok = p.n_views > 0
    assert ok.sum() > 1000
    # the views with an error are the views used: their count is n_views, their mean the mean error
    np.testing.assert_array_equal(np.isfinite(ec).sum(-1)[ok], p.n_views[ok])
    np.testing.assert_allclose(np.nanmean(ec[ok], -1), p.reproj_err_px[ok], rtol=1e-5, atol=1e-4)
    assert not np.isfinite(ec[~ok]).any()


def test_poses3d_without_per_camera_errors_still_loads(tmp_path):
    from roomcap.triangulate.poses3d import Poses3D

    lay = synthetic_session(tmp_path / "s", seconds=1.0)
    d = dict(np.load(lay.poses3d))
    del d["cameras"], d["reproj_err_cam_px"]
    np.savez(lay.poses3d, **d)  # a file written before these keys existed
    p = Poses3D.load(lay.poses3d)
    assert p.cameras is None and p.reproj_err_cam_px is None
    data = report_data(write_report(lay))
    assert (
        data["quality"]["cameras"] == []
        and "rerun the triangulate stage" in data["quality"]["per_camera_note"]
    )
    assert data["quality"]["mean_px"] is not None


# ----------------------------------------------------------------------------- report data


def test_report_figures_equal_what_triangulation_wrote(tmp_path):
    lay = synthetic_session(tmp_path / "s")
    data = report_data(write_report(lay))
    want, mean_all = independent_camera_figures(lay.poses3d)
    got = {c["name"]: (c["mean_px"], c["median_px"], c["p90_px"], c["n"]) for c in data["quality"]["cameras"]}
    assert got == want
    assert data["quality"]["mean_px"] == mean_all
    d = np.load(lay.poses3d)
    err = np.where(d["n_views"] > 0, d["reproj_err_px"], np.nan).astype(np.float64)
    per_joint = [round(float(np.nanmean(err[..., j])), 3) for j in range(err.shape[-1])]
    assert data["quality"]["per_joint_mean_px"] == per_joint


def test_track_events_find_unobserved_frames_and_a_swap(tmp_path):
    lay = make_session(tmp_path / "s", n_people=2, T=60)
    tf = TrackFile.load(lay.tracks)
    xyz, flags = tf.xyz_m.copy(), tf.flags.copy()
    xyz[40:, [0, 1]] = xyz[40:, [1, 0]]  # identities exchanged at frame 40 ...
    flags[10:16, 0] = PREDICTED  # ... and track 0 carried through frames 10-15
    import dataclasses

    tf = dataclasses.replace(tf, xyz_m=xyz, flags=flags)
    ev = track_events(tf, ReportConfig(swap_radius_m=0.5))
    assert ev["unobserved"][0] == [[10, 15]] and ev["unobserved"][1] == []
    assert ev["predicted_frames"] == [6, 0] and ev["interpolated_frames"] == [0, 0]
    assert {(j["id"], j["frame"]) for j in ev["jumps"]} == {(0, 40), (1, 40)}
    assert {j["swap_with"] for j in ev["jumps"]} == {0, 1}
    # the circle walk itself (0.16 m per frame at 25 fps = 3.9 m/s) is not a jump
    ev0 = track_events(TrackFile.load(lay.tracks), ReportConfig())
    assert ev0["jumps"] == []


def test_warnings_logged_by_a_stage_reach_the_report(tmp_path):
    from roomcap.pipeline.cli import main as reprocess

    lay = synthetic_session(tmp_path / "s", seconds=1.0)
    lay.detections("cam01").unlink()  # the rig has a camera without detections: triangulate warns
    assert reprocess([str(lay.root), "--stages", "triangulate,track,report", "--workers", "1"]) == 0
    saved = json.loads((lay.root / ".roomcap" / "warnings" / "triangulate.json").read_text())
    assert any("cam01" in m and "no detections" in m for m in saved)
    # a rerun of the report alone still shows what triangulate logged when it made its output
    assert reprocess([str(lay.root), "--stages", "report", "--workers", "1", "--force", "--overlay"]) == 0
    data = report_data(lay.report_html)
    assert sorted(p.name for p in (lay.root / "report" / "overlay").iterdir()) == [
        "cam00.mp4",
        "cam02.mp4",
        "cam03.mp4",
    ]
    assert any(w["stage"] == "triangulate" and "cam01" in w["message"] for w in data["warnings"])


def test_image_budget_samples_frames_and_bounds_the_file(tmp_path):
    """Videos in raw/: the filmstrip embeds JPEG frames; a smaller budget samples fewer frames."""
    lay = synthetic_session(tmp_path / "s", seconds=4.0, cams=3)
    rng = np.random.default_rng(0)
    for cam in lay.detection_cameras():
        w, h = (1280, 720)
        lay.raw_dir.mkdir(exist_ok=True)
        wr = cv2.VideoWriter(str(lay.raw_dir / f"{cam}.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), 25, (w, h))
        base = rng.integers(0, 255, (h // 8, w // 8, 3), np.uint8)
        for t in range(100):
            wr.write(cv2.resize(np.roll(base, t, 1), (w, h), interpolation=cv2.INTER_NEAREST))
        wr.release()
    full = report_data(write_report(lay, config=ReportConfig(image_budget_bytes=100_000_000)))
    assert len(full["views"]["frames"]) == 100 and all(c["images"][0] for c in full["views"]["cameras"])
    budget = 2_500_000
    path = write_report(lay, config=ReportConfig(image_budget_bytes=budget))
    small = report_data(path)
    n = len(small["views"]["frames"])
    assert 8 <= n < 100
    jpeg = sum(len(u) * 3 / 4 for c in small["views"]["cameras"] for u in c["images"] if u)
    assert jpeg < 1.3 * budget, f"{jpeg:.0f} JPEG bytes for a budget of {budget}"
    # evenly spread over the session, first and last frame included
    fr = small["views"]["frames"]
    assert fr[0] == 0 and fr[-1] == 99 and np.ptp(np.diff(fr)) <= 1


def test_overlay_videos_without_video_draw_on_a_blank_canvas(tmp_path):
    lay = synthetic_session(tmp_path / "s", seconds=1.0, cams=2)
    paths = write_overlay_videos(lay)
    assert [p.name for p in paths] == ["cam00.mp4", "cam01.mp4"]
    cap = cv2.VideoCapture(str(paths[0]))
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == 25
    ok, img = cap.read()
    cap.release()
    assert ok and img.std() > 3  # skeletons drawn on the dark canvas


# ----------------------------------------------------------------------------- in the browser


@need_chromium
def test_report_renders_people_without_errors(tmp_path):
    lay = make_session(tmp_path / "s1")
    path = write_report(lay, title="synthetic")
    text = path.read_text()
    assert "http://" not in text and "https://" not in text  # self-contained: nothing to fetch
    img, dom = render_in_browser(path, tmp_path)
    assert 'data-rendered="3"' in dom, "the viewer script did not finish"
    assert page_errors(dom) == "", f"page errors: {page_errors(dom)}"
    # the viewer: the dark canvas region; people are drawn in their colours inside it
    dark = np.all(np.abs(img.astype(int) - [28, 20, 16]) < 6, axis=-1)  # BGR of #10141c
    ys, xs = np.nonzero(dark)
    assert len(ys) > 100_000, "no viewer canvas on the page"
    viewer = img[ys.min() : ys.max(), xs.min() : xs.max()].astype(int)
    person_bgr = [(75, 25, 230), (75, 180, 60), (216, 99, 67)]  # #e6194b #3cb44b #4363d8
    hits = [int(np.all(np.abs(viewer - c) < 40, axis=-1).sum()) for c in person_bgr]
    assert min(hits) > 50, f"people not drawn in the viewer (pixels per person colour: {hits})"


@need_chromium
def test_synthetic_report_in_browser_filmstrips_and_tables(tmp_path):
    lay = synthetic_session(tmp_path / "s")
    path = write_report(lay)
    img, dom = render_in_browser(path, tmp_path, height=4200)
    assert page_errors(dom) == "", f"page errors: {page_errors(dom)}"
    assert 'data-films="4"' in dom
    for cam, (x, y, w, h) in film_rects(dom).items():
        crop = img[y : y + h, x : x + w]
        cv2.imwrite(str(tmp_path / f"film_{cam}.png"), crop)
        assert crop.size and crop.std() > 8, f"{cam}: the camera view is blank"
    want, _ = independent_camera_figures(lay.poses3d)
    rows = dom_cell_values(dom, "reprojCams")
    assert [r[1:4] for r in rows[: len(want)]] == [list(v[:3]) for v in want.values()]


def test_report_without_tracks_still_writes(tmp_path):
    lay = SessionLayout(tmp_path / "empty")
    lay.root.mkdir()
    path = write_report(lay, title="empty")
    data = report_data(path)
    assert data["tracks"] is None and any(p["title"] == "No tracks" for p in data["problems"])


# ----------------------------------------------------------------------------- the multi-person demo


@pytest.mark.slow
@need_chromium
def test_multi_person_demo_report(tmp_path):
    """The Pose2Sim multi-person demo (4 portrait videos, first 12 frames): a filmstrip per camera with the
    video and the overlays, the reprojection figures as triangulate wrote them, the calibration's figures,
    no page errors, and every track inside some camera's field of view in the room from above (the
    bystander was drawn outside all of them: the old sectors were cut at 2.5 m)."""
    from matplotlib.path import Path as PolyPath

    from roomcap.pipeline.cli import main as reprocess

    trial = need_shared("data", "pose2sim", "demo-wheel-0.10.49", "Demo_MultiPerson")
    out = tmp_path / "out"
    assert reprocess([str(trial), "--out", str(out), "--workers", "1", "--max-frames", "12"]) == 0
    lay = SessionLayout(out / trial.name)
    data = report_data(lay.report_html)
    assert lay.report_html.stat().st_size < 30e6
    assert [c["name"] for c in data["views"]["cameras"]] == ["cam01", "cam02", "cam03", "cam04"]
    assert all(all(c["images"]) for c in data["views"]["cameras"])
    # the calibration's own figures: the Qualisys file's per-camera residuals
    assert sorted(data["rig"]["figures"]["cameras"]) == ["cam01", "cam02", "cam03", "cam04"]
    assert data["rig"]["figures"]["cameras"]["cam01"]["avg_residual"] == 0.402
    img, dom = render_in_browser(lay.report_html, tmp_path, height=4600, name="demo")
    assert page_errors(dom) == "", f"page errors: {page_errors(dom)}"
    assert 'data-films="4"' in dom
    for cam, (x, y, w, h) in film_rects(dom).items():
        crop = img[y : y + h, x : x + w]
        cv2.imwrite(str(tmp_path / f"demo_film_{cam}.png"), crop)
        assert crop.std() > 20, f"{cam}: the filmstrip is blank"
    want, mean_all = independent_camera_figures(lay.poses3d)
    rows = dom_cell_values(dom, "reprojCams")
    assert [r[1:4] for r in rows[:4]] == [list(v[:3]) for v in want.values()]
    assert rows[4][1] == mean_all
    # room from above: every tracked root lies in the footprint of at least one camera
    polys = [PolyPath(np.asarray(c["footprint_m"])) for c in data["rig"]["cameras"]]
    xyz = np.load(lay.tracks)["xyz_m"]
    pelvis = xyz[:, :, CANONICAL.joint_names.index("pelvis"), :2].reshape(-1, 2)
    pelvis = pelvis[np.isfinite(pelvis).all(-1)]
    inside = np.any([p.contains_points(pelvis) for p in polys], axis=0)
    assert inside.mean() > 0.99, f"{(~inside).sum()} of {len(inside)} track positions outside every camera"


def test_merge_whose_merged_hypothesis_is_dropped_later():
    """A merged into by B (disjoint cameras), then A dropped for C (shared cameras, more views): nothing
    is left to re-triangulate, which must work with the per-camera rows of V (it once raised)."""
    from roomcap.synthetic.rigs import ring_rig as rr
    from roomcap.triangulate.reconstruct import FrameReconstructor, TriangulateConfig

    rig = rr(4, radius_m=4.0)
    X = np.zeros((19, 3))
    X[:, 2] = np.linspace(0.1, 1.7, 19)
    X[:, 0] = np.linspace(-0.2, 0.2, 19)
    xy = np.full((4, 2, 19, 2), np.nan)
    for c in range(4):
        xy[c, 0] = rig.cameras[c].project(X)
    xy[:3, 1] = xy[:3, 0] + 3.0  # a second, slightly shifted detection in cameras 0-2
    sc = np.where(np.isfinite(xy[..., 0]), 0.9, 0.0)
    cfg = TriangulateConfig(limb_check=False)  # a stick, not a body
    rec = FrameReconstructor(rig.projection_matrices(), None, cfg, joint_names=CANONICAL.joint_names)
    Z = rec._planes(xy, sc, np.isfinite(xy).all(-1))
    H = np.array([[0, 0, -1, -1], [-1, -1, 0, 0], [1, 1, 1, -1]])  # A, B, C
    S = np.zeros(H.shape, bool)
    V, keep = rec._triangulate(Z, H, S)
    assert V.shape == (8 + 4, 3, 19) and keep.all()
    H2, _, V2, _ = rec._merge_duplicates(Z, H.copy(), S.copy(), V.copy(), keep.copy())
    np.testing.assert_array_equal(H2, H[2:])
    assert V2.shape == (12, 1, 19)


# ----------------------------------------------------------------------------- the forecast's paths


def test_report_forecast_paths_with_the_samples_spread(tmp_path):
    """A stochastic model's preview carries its samples; the report gives each person's floor path, the
    samples' paths and their spread; a deterministic one says so (no spread drawn) and the page renders
    both without errors."""
    from roomcap.forecast.runtime.preview import CHECKPOINT_DIR, write_preview

    ckpt = CHECKPOINT_DIR / "intention_cmuall.pt"
    if not ckpt.exists():
        pytest.skip(f"{ckpt} not shipped in this checkout")
    lay = make_session(tmp_path / "sto", n_people=3, T=60)
    out = lay.root / "forecast" / "preview.npz"
    out.parent.mkdir(parents=True)
    write_preview(lay.tracks, out, 1.0, str(ckpt), n_samples=4)
    d = np.load(out)
    K, H = 3, len(d["t_s"])
    assert bool(d["stochastic"]) and d["samples_xyz_m"].shape == (4, K, H, 19, 3)
    assert np.array_equal(d["samples_xyz_m"][0], d["xyz_m"], equal_nan=True)
    f = report_data(write_report(lay))["forecast"]
    assert f["stochastic"] is True
    assert np.asarray(f["path"], float).shape == (K, H, 2)
    paths = np.asarray(f["sample_paths"], float)
    spread = np.asarray(f["spread_m"], float)
    assert paths.shape == (K, 4, H, 2) and spread.shape == (K, H)
    assert np.isfinite(paths).all() and np.isfinite(spread).all()
    # the spread is the samples' RMS distance from their mean, and the samples differ
    want = np.sqrt(((paths - paths.mean(1, keepdims=True)) ** 2).sum(-1).mean(1))
    assert np.allclose(spread, want, atol=2e-3) and spread[:, -1].max() > 1e-3
    # the path is the floor point under the pelvis of the forecast poses
    pel = CANONICAL.joint_names.index("pelvis")
    assert np.allclose(f["path"], d["xyz_m"][:, :, pel, :2], atol=1e-3)

    det = make_session(tmp_path / "det", n_people=3, T=60)
    (det.root / "forecast").mkdir()
    write_preview(det.tracks, det.root / "forecast" / "preview.npz", 1.0, "constant_velocity")
    g = report_data(write_report(det))["forecast"]
    assert g["stochastic"] is False and g["sample_paths"] is None and g["spread_m"] is None
    assert np.asarray(g["path"], float).shape == (K, 25, 2)
    if CHROMIUM is None:
        pytest.skip("headless Chromium not installed")
    for name, session in (("sto", lay), ("det", det)):
        _, dom = render_in_browser(session.report_html, tmp_path, height=1600, name=name)
        assert page_errors(dom) == "", f"{name}: page errors: {page_errors(dom)}"
        assert 'id="fcsec" style="display: block;"' in dom, f"{name}: no forecast paths panel"
        note = dom.split('id="layoutNote"', 1)[1].split("</div>", 1)[0]
        assert ("4 samples" in note) if name == "sto" else ("deterministic" in note), note


def test_whole_body_report_draws_the_hands(tmp_path):
    """A whole-body session (2D in body19_hands, triangulated with the whole_body skeleton, tracked): the
    report's 3D data has the 42 hand joints, every camera's overlay has the detected hands (matched to
    the track) and the track's hands reprojected, within a few pixels of each other; the hand bones hang
    off the wrists. A body-only session's overlays have no hand keys (its report unchanged); the page
    draws without errors."""
    from hands_helpers import SK, wholebody_session

    from roomcap.calibrate.camera import CameraRig
    from roomcap.keypoints.detections import Detections
    from roomcap.keypoints.skeletons import HANDS
    from roomcap.pipeline.report.views import HAND2D

    lay, X = wholebody_session(tmp_path / "wb", T=12)
    path = write_report(lay, title="whole body")
    d = report_data(path)
    T3 = d["tracks"]
    assert T3["joint_names"][-42:] == list(HANDS)
    xyz = np.asarray(T3["xyz"], np.float64)
    assert np.isfinite(xyz[:, 0, -42:]).all()
    par = {T3["joint_names"][c]: T3["joint_names"][p] for c, p in enumerate(T3["parents"]) if p >= 0}
    assert par["left_hand_root"] == "left_wrist" and par["right_thumb1"] == "right_hand_root"
    V = d["views"]
    assert V["hand_names"] == list(HAND2D) and len(V["hand_parents"]) == 44
    assert V["hand_names"][V["hand_parents"][HAND2D.index("right_hand_root")]] == "right_wrist"
    assert V["hand_names"][V["hand_parents"][HAND2D.index("left_pinky_finger4")]] == "left_pinky_finger3"
    # the overlays' hands: the detections' own 2D and the track's hands projected by the rig (rounded px)
    rig, tf = CameraRig.load(lay.rig_toml), TrackFile.load(lay.tracks)
    hj = [tf.joint_names.index(n) for n in HAND2D]
    dj = [SK.index(n) for n in HAND2D]
    for cam in V["cameras"]:
        assert len(cam["overlays"]) == 12
        det2d = Detections.load(lay.detections(cam["name"]))
        for t, ov in enumerate(cam["overlays"]):
            (k, det), (kp, proj) = ov["hdet"][0], ov["hproj"][0]
            assert k == kp == 0 and len(det) == len(proj) == 88
            a = np.asarray(det, float).reshape(44, 2)
            b = np.asarray(proj, float).reshape(44, 2)
            want = rig[cam["name"]].project(tf.xyz_m[t, 0, hj].astype(np.float64))
            assert np.abs(b - want).max() <= 0.51
            src = det2d.xy_px[t, 0, dj]
            assert np.abs(a - src).max() <= 0.51
            assert np.median(np.linalg.norm(a[2:] - b[2:], axis=-1)) < 40  # the same hands
    body = report_data(write_report(make_session(tmp_path / "b", n_people=1, T=10)))
    assert "hand_parents" not in (body["views"] or {})
    if CHROMIUM is not None:
        img, dom = render_in_browser(path, tmp_path, height=1800)
        assert page_errors(dom) == "", f"page errors: {page_errors(dom)}"


def test_whole_body_overlay_video_draws_the_hands(tmp_path):
    """The overlay video of a whole-body session draws the finger bones: pixels around the projected
    hands differ from the same frame drawn without the hands."""
    from hands_helpers import wholebody_session

    from roomcap.pipeline.report.inputs import _load
    from roomcap.pipeline.report.overlay_video import draw_overlay
    from roomcap.pipeline.report.views import HAND2D_PARENTS, _Overlay

    lay, _ = wholebody_session(tmp_path / "wb", T=4)
    (path, *_) = write_overlay_videos(lay)
    cap = cv2.VideoCapture(str(path))
    ok, img = cap.read()
    cap.release()
    assert ok
    ov = _Overlay(_load(lay), ReportConfig())
    cam = ov.cams[0]
    det, proj = ov.detections(cam, 0), ov.project(cam, np.asarray([0]))[0]
    hp = ov.project(cam, np.asarray([0]), hands=True)[0]
    blank = np.full_like(img, 24)
    plain = draw_overlay(blank.copy(), det, ov.match(det, proj), proj, ov.parents)
    with_hands = draw_overlay(
        blank.copy(),
        det,
        ov.match(det, proj),
        proj,
        ov.parents,
        (ov.detections(cam, 0, hands=True), hp, HAND2D_PARENTS),
    )
    changed = np.abs(with_hands.astype(int) - plain.astype(int)).sum(-1) > 30
    assert changed.sum() > 100  # finger bones drawn
    # the video's frame (MP4V-compressed) shows them where they were drawn
    on = np.abs(img.astype(int) - 24).sum(-1) > 60
    assert (on & changed).sum() > 0.5 * changed.sum()
