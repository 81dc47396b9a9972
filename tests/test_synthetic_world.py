"""Synthetic world: rigs, scenes and rendering checked against their own ground truth."""

from __future__ import annotations

import time

import numpy as np
import pytest

from roomcap.calibrate.camera import CameraRig
from roomcap.keypoints.detections import Detections
from roomcap.keypoints.skeletons import CANONICAL
from roomcap.synthetic import render as R
from roomcap.synthetic import rigs, world

J = {n: i for i, n in enumerate(CANONICAL.joint_names)}
CLEAN = R.RenderConfig(occlusion_people=False, occlusion_furniture=False, shuffle=True)


def _rows(rendering, c):
    """(t, row, person) of every ground-truth detection row of camera c."""
    gi = rendering.gt_index[c]
    t, k = np.nonzero(gi >= 0)
    return t, k, gi[t, k]


def _static_scene(room, positions_xy, T=3, fps=25.0):
    """People standing still (procedural pose of frame 0) at ``positions_xy``, facing +x."""
    rng = np.random.default_rng(0)
    pose = world.procedural_walk(2, fps, rigs.ring_room(10.0), rng)[0]
    pose = pose - pose[J["pelvis"]] * np.array([1.0, 1.0, 0.0])
    gt = np.stack([np.stack([pose + [x, y, 0.0] for x, y in positions_xy])] * T)
    cfg = world.SceneConfig(n_people=len(positions_xy), duration_s=T / fps, fps=fps, motion="procedural")
    return world.Scene(gt, np.arange(len(positions_xy)), fps, room, ("static",) * len(positions_xy), cfg)


def _one_camera_rig(center, target):
    return CameraRig((rigs.make_camera("cam00", center, target, (1280, 720), 70.0),))


@pytest.fixture(scope="module")
def ring_scene():
    room = rigs.ring_room(3.0)
    scene = world.make_scene(room, world.SceneConfig(n_people=3, duration_s=2.0, fps=25, seed=3))
    return rigs.ring_rig(6, 3.0, distortion=True), scene


def test_scene_ground_truth_is_plausible(ring_scene):
    rig, scene = ring_scene
    g = scene.gt_xyz_m
    assert g.shape == (50, 3, 19, 3) and scene.present.all()
    x0, x1, y0, y1 = scene.room.bounds_m
    assert np.all((g[..., 0] >= x0) & (g[..., 0] <= x1) & (g[..., 1] >= y0) & (g[..., 1] <= y1))
    ank = np.minimum(g[..., J["left_ankle"], 2], g[..., J["right_ankle"], 2])
    assert np.all(np.percentile(ank, 5, axis=0) < 0.15) and np.all(ank > -0.05)  # feet on the floor
    if "procedural" not in scene.clip_names:  # mocap found: distinct clips
        assert len(set(scene.clip_names)) == 3


def test_noise_free_render_equals_projection(ring_scene):
    rig, scene = ring_scene
    r = R.render(scene, rig, CLEAN)
    for c, det in enumerate(r.detections):
        assert isinstance(det, Detections) and det.camera == rig.names[c]
        t, k, p = _rows(r, c)
        want = rig[c].project(scene.gt_xyz_m[t, p].reshape(-1, 3)).reshape(len(t), 19, 2)
        got = det.xy_px[t, k].astype(np.float64)
        seen = np.isfinite(got[..., 0])
        assert seen.mean() > 0.9
        np.testing.assert_allclose(got[seen], want[seen], atol=1e-3)  # float32 storage
        # every GT joint inside the image is reported (no faults configured)
        w, h = rig[c].size_wh
        inside = (
            (want[..., 0] >= -0.5)
            & (want[..., 0] <= w - 0.5)
            & (want[..., 1] >= -0.5)
            & (want[..., 1] <= h - 0.5)
        )
        assert np.array_equal(seen, inside)
        assert np.all(det.score[t, k][seen] > 0.5)


def test_detection_order_is_shuffled(ring_scene):
    rig, scene = ring_scene
    r = R.render(scene, rig, CLEAN)
    gi = r.gt_index[0]
    assert any(not np.array_equal(row[row >= 0], np.sort(row[row >= 0])) for row in gi)


def test_seeds_reproducible(ring_scene):
    rig, scene = ring_scene
    cfg = R.RenderConfig(noise_px=2.0, missed_joint_rate=0.1, flip_rate=0.05, false_positive_rate=0.2)
    a, b = R.render(scene, rig, cfg), R.render(scene, rig, cfg)
    c = R.render(scene, rig, cfg.replace(seed=1))
    for da, db, dc in zip(a.detections, b.detections, c.detections, strict=True):
        np.testing.assert_array_equal(da.xy_px, db.xy_px)
        assert da.xy_px.shape != dc.xy_px.shape or not np.array_equal(da.xy_px, dc.xy_px, equal_nan=True)
    s2 = world.make_scene(scene.room, scene.config)
    np.testing.assert_array_equal(s2.gt_xyz_m, scene.gt_xyz_m)


def test_flips_swap_left_right(ring_scene):
    rig, scene = ring_scene
    r0 = R.render(scene, rig, CLEAN)
    r1 = R.render(scene, rig, CLEAN.replace(flip_rate=1.0))
    c = 0
    t, k, p = _rows(r1, c)
    want = r0.gt_xy_px[c][t, p][:, CANONICAL.flip_index]
    got = r1.detections[c].xy_px[t, k]
    seen = np.isfinite(got[..., 0])
    np.testing.assert_allclose(got[seen], want[seen], atol=1e-3)
    assert not np.allclose(got[seen], r0.gt_xy_px[c][t, p][seen], atol=1.0)


def test_furniture_hides_the_legs():
    # a camera at 1 m height looks along +x at a person 2 m behind a 1.2 m high box
    room = rigs.Room("test", (-5, 5, -5, 5), 3.0, (rigs.Box("counter", (-0.5, -1, 0), (0.5, 1, 1.2)),))
    scene = _static_scene(room, [(2.0, 0.0)])
    rig = _one_camera_rig((-3.0, 0.0, 1.0), (2.0, 0.0, 1.0))
    vis = R.render(scene, rig, R.RenderConfig()).visible[0]
    assert not vis[:, 0, [J["left_ankle"], J["right_knee"], J["pelvis"]]].any()
    assert vis[:, 0, [J["nose"], J["left_eye"]]].all()
    vis_off = R.render(scene, rig, R.RenderConfig(occlusion_furniture=False)).visible[0]
    assert vis_off.all()


def test_people_hide_people_behind_them():
    room = rigs.Room("empty", (-6, 6, -6, 6))
    scene = _static_scene(room, [(0.0, 0.0), (2.5, 0.0)])  # person 1 right behind person 0
    rig = _one_camera_rig((-3.0, 0.0, 1.2), (0.0, 0.0, 1.0))
    vis = R.render(scene, rig, R.RenderConfig()).visible[0]
    assert vis[:, 0].all()  # the front person is fully visible
    # the torso behind is hidden   (measured 19/19 joints hidden)
    assert not vis[:, 1, [J["neck"], J["pelvis"]]].any()
    assert R.render(scene, rig, R.RenderConfig(occlusion_people=False)).visible[0].all()


def test_faults_have_their_rates():
    rig, room = rigs.kitchen(6)
    scene = world.make_scene(room, world.SceneConfig(n_people=4, duration_s=4, fps=25, seed=5))
    base = R.render(scene, rig, R.RenderConfig())
    r = R.render(
        scene, rig, R.RenderConfig(missed_joint_rate=0.2, false_positive_rate=0.3, missed_detection_rate=0.1)
    )
    n_vis = base.visible.sum()
    n_rep = sum(
        np.isfinite(d.xy_px[..., 0])[g >= 0].sum() for d, g in zip(r.detections, r.gt_index, strict=True)
    )
    assert 0.65 < n_rep / n_vis < 0.78  # 0.8 x 0.9 = 0.72 expected   (measured 0.727)
    n_fp = sum((g == -1).sum() for g in r.gt_index)
    # 0.3 drawn per camera and frame, some fall outside the image   (measured 0.25)
    assert 0.15 < n_fp / (len(rig) * scene.n_frames) < 0.32
    # scores: noisy joints score lower
    rn = R.render(scene, rig, R.RenderConfig(noise_px=8.0))
    s_clean = np.concatenate([d.score[d.score > 0] for d in base.detections]).mean()
    s_noisy = np.concatenate([d.score[d.score > 0] for d in rn.detections]).mean()
    assert s_noisy < s_clean - 0.1  # (measured 0.93 vs 0.45)


def test_time_offset_and_drift():
    rig = rigs.ring_rig(3, 3.0)
    scene = world.make_scene(rigs.ring_room(3.0), world.SceneConfig(n_people=1, duration_s=2, fps=25, seed=2))
    off = (0.0, 0.5, -2.25)
    r = R.render(scene, rig, CLEAN.replace(time_offsets_frames=off, time_drifts_ppm=(0.0, 0.0, 1000.0)))
    np.testing.assert_allclose(r.time_offsets_frames, off)
    c = 1
    t, k, p = _rows(r, c)
    g = scene.gt_xyz_m[:, 0]
    X = 0.5 * (g[t] + g[np.minimum(t + 1, len(g) - 1)])
    want = rig[c].project(X.reshape(-1, 3)).reshape(len(t), 19, 2)
    got = r.detections[c].xy_px[t, k]
    ok = np.isfinite(got[..., 0])
    np.testing.assert_allclose(got[ok], want[ok], atol=1e-3)
    assert t.max() < scene.n_frames - 1  # the last frame is beyond the scene for a +0.5 frame offset
    assert r.detections[2].xy_px.shape[0] == scene.n_frames and r.gt_index[2][0].max() < 0  # -2.25: no GT


def test_people_enter_and_leave():
    rig, room = rigs.kitchen(4)
    cfg = world.SceneConfig(
        n_people=6,
        duration_s=8,
        fps=10,
        seed=4,
        enter_leave=True,
        enter_leave_fraction=1.0,
        return_fraction=1.0,
    )
    scene = world.make_scene(room, cfg)
    pres = scene.present
    assert not pres.all() and pres.any(0).all()
    assert (pres.sum(0) >= cfg.min_present_s * cfg.fps).all()
    r = R.render(scene, rig, CLEAN)
    for g in r.gt_index:
        t, k = np.nonzero(g >= 0)
        assert pres[t, g[t, k]].all()  # nobody is detected while absent


def test_procedural_fallback_without_mocap(tmp_path, monkeypatch):
    monkeypatch.setenv("ROOMCAP_MOCAP", str(tmp_path))  # an empty mocap folder
    rig, room = rigs.kitchen(3)
    scene = world.make_scene(room, world.SceneConfig(n_people=2, duration_s=3, fps=25, seed=0))
    assert scene.clip_names == ("procedural", "procedural")
    g = scene.gt_xyz_m
    speed = np.linalg.norm(np.diff(g[:, :, J["pelvis"], :2], axis=0), axis=-1) * 25
    assert 0.2 < np.median(speed) < 1.6 and np.isfinite(g).all()
    with pytest.raises(FileNotFoundError, match="ROOMCAP_MOCAP"):
        world.make_scene(room, world.SceneConfig(n_people=1, motion="mocap"))


def test_coco17_output_and_config_errors(ring_scene):
    rig, scene = ring_scene
    r = R.render(scene, rig, CLEAN.replace(skeleton="coco17"))
    assert r.detections[0].xy_px.shape[2] == 17
    with pytest.raises(ValueError, match="valid keys"):
        R.RenderConfig.from_dict({"noise": 1.0})
    with pytest.raises(ValueError, match="flip_rate"):
        R.RenderConfig(flip_rate=2.0)


def test_write_session_round_trip(tmp_path, ring_scene):
    rig, scene = ring_scene
    r = R.render(scene, rig, R.RenderConfig(noise_px=1.0, false_positive_rate=0.1))
    lay = world.write_session(scene, r, rig, tmp_path / "s")
    assert CameraRig.load(lay.rig_toml).names == rig.names
    assert lay.detection_cameras() == sorted(rig.names)
    d = Detections.load(lay.detections("cam01"))
    np.testing.assert_array_equal(d.xy_px, r.detections[1].xy_px)
    gt = world.load_gt(lay.root)
    np.testing.assert_array_equal(gt["gt_xyz_m"], scene.gt_xyz_m)
    np.testing.assert_array_equal(gt["gt_index_cam01"], r.gt_index[1])


def test_kitchen_12x8x10s_renders_in_seconds():
    t0 = time.perf_counter()
    rig, room = rigs.kitchen(12)
    scene = world.make_scene(room, world.SceneConfig(n_people=8, duration_s=10, fps=25, seed=0))
    r = R.render(
        scene,
        rig,
        R.RenderConfig(
            noise_px=3,
            missed_joint_rate=0.1,
            flip_rate=0.02,
            false_positive_rate=0.1,
            missed_detection_rate=0.02,
        ),
    )
    dt = time.perf_counter() - t0
    assert len(r.detections) == 12 and scene.gt_xyz_m.shape == (250, 8, 19, 3)
    hidden = 1 - r.visible.sum() / np.isfinite(r.gt_xy_px[..., 0]).sum()
    # furniture + people occlusion   (measured 0.14: 0.08 furniture only, 0.06 people only)
    assert 0.05 < hidden < 0.5
    assert dt < 10.0  # measured 1.3-1.7 s (warm clip cache)


def test_cli_writes_a_session(tmp_path):
    from roomcap.synthetic.__main__ import main

    assert main([str(tmp_path / "s"), "--rig", "ring", "--cams", "3", "--people", "2", "--seconds", "1"]) == 0
    names = sorted(p.name for p in (tmp_path / "s" / "keypoints").iterdir())
    assert names == ["cam00.npz", "cam01.npz", "cam02.npz"]
    assert world.load_gt(tmp_path / "s")["gt_xyz_m"].shape == (25, 2, 19, 3)
