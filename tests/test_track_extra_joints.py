"""The particle tracker carries the whole-body joints (feet, BODY_25B's upper neck and head top) that the
greedy tracker carries: triangulated per track after identities are assigned (track.extra_joints)."""

from __future__ import annotations

import numpy as np
import pytest
from triangulate_helpers import FOOT_HEAD_OFFSETS

from roomcap.capture.session import SessionLayout
from roomcap.keypoints.detections import Detections
from roomcap.keypoints.skeletons import CANONICAL, SKELETONS, whole_body
from roomcap.track.extra_joints import ExtraJointsConfig, assign_views, attach_joints
from roomcap.track.stage import ParticleTrackConfig, track_session_particle
from roomcap.track.trackfile import OBSERVED, TrackFile


def _body25b(gt19: np.ndarray) -> np.ndarray:
    """(T,P,25,3) BODY_25B joints from body19 ground truth (extra joints at fixed offsets)."""
    B = SKELETONS["body25b"]
    out = np.full(gt19.shape[:2] + (B.n_joints, 3), np.nan)
    for j, name in enumerate(B.joint_names):
        if name in CANONICAL.joint_names:
            out[:, :, j] = gt19[:, :, CANONICAL.index(name)]
        else:
            par, off = FOOT_HEAD_OFFSETS[name]
            out[:, :, j] = gt19[:, :, CANONICAL.index(par)] + off
    return out


def _session(tmp_path, seconds=2.0, noise_px=1.0):
    from roomcap.synthetic.rigs import ring_rig, ring_room
    from roomcap.synthetic.world import SceneConfig, make_scene

    fps = 25.0
    rig = ring_rig(4, radius_m=4.0)
    scene = make_scene(
        ring_room(3.0), SceneConfig(n_people=2, duration_s=seconds, fps=fps, seed=3, motion="procedural")
    )
    X = _body25b(scene.gt_xyz_m)  # (T,P,25,3)
    T, P, J = X.shape[:3]
    lay = SessionLayout(tmp_path)
    rig.save(lay.calib_dir / "rig.toml")
    rng = np.random.default_rng(0)
    for c, cam in enumerate(rig):
        xy = rig.project(X.reshape(-1, 3))[c].reshape(T, P, J, 2)
        xy = xy + rng.normal(0, noise_px, xy.shape)
        order = rng.permuted(np.tile(np.arange(P), (T, 1)), axis=1)  # slots are not identities
        xy = np.take_along_axis(xy, order[:, :, None, None], 1)
        Detections(
            camera=cam.name,
            skeleton="body25b",
            frame_index=np.arange(T),
            t_ns=(np.arange(T) * 1e9 / fps).astype(np.int64),
            xy_px=xy,
            score=np.full(xy.shape[:-1], 0.9),
            boxes=np.full(xy.shape[:2] + (5,), np.nan),
        ).save(lay.detections(cam.name))
    return lay, X, scene.gt_xyz_m


@pytest.mark.slow
def test_particle_tracker_carries_the_feet(tmp_path):
    lay, X, gt19 = _session(tmp_path)
    opts = {"motion": "constant_velocity", "n_samples": 100, "skeleton": "whole_body"}
    tf = TrackFile.load(track_session_particle(lay.root, opts))
    wb = whole_body(["body25b"])
    assert tf.joint_names == wb.joint_names and tf.parents.tolist() == list(wb.parents)
    assert tf.n_tracks == 2
    B = SKELETONS["body25b"]
    # each track is one person: match it by its body19 joints, then its feet must be that person's
    for k in range(tf.n_tracks):
        d = np.nanmean(np.linalg.norm(tf.xyz_m[:, k, None, :19] - gt19, axis=-1), axis=(0, 2))
        p = int(np.argmin(d))
        for name in ("left_heel", "right_big_toe", "left_small_toe", "head_top", "upper_neck"):
            got = tf.xyz_m[:, k, wb.index(name)]
            known = np.isfinite(got).all(-1)
            assert known.mean() > 0.9, name  # over the frames the track covers
            err = np.linalg.norm(got[known] - X[known, p, B.index(name)], axis=-1)
            assert np.median(err) < 0.008 and err.max() < 0.03, (name, np.median(err), err.max())
            j = wb.index(name)
            assert np.isfinite(tf.std_m[known, k, j]).all() and (tf.std_m[known, k, j] < 0.05).all()
            assert (tf.flags[known, k, j] & OBSERVED).all() and (tf.confidence[known, k, j] > 0.5).all()
    # the body19 joints are the particle filter's, unchanged by the attachment
    tf19 = TrackFile.load(track_session_particle(lay.root, {"motion": "constant_velocity", "n_samples": 100}))
    assert tf19.joint_names == CANONICAL.joint_names
    np.testing.assert_allclose(tf.xyz_m[:, :, :19], tf19.xyz_m, atol=1e-6)


def test_assign_views_gates_and_swaps():
    P = np.array([[[1000.0, 0, 500, 0], [0, 1000, 500, 0], [0, 0, 1, 4]]])  # one camera, 4 m away
    rng = np.random.default_rng(1)
    X = np.stack([rng.normal(0, 0.3, (19, 3)), rng.normal(0, 0.3, (19, 3)) + (1.5, 0, 0)])  # two tracks
    from roomcap.triangulate.geometry import project

    uv = project(P, X.reshape(-1, 3))[0].reshape(2, 19, 2)
    xy = np.stack([uv[1], uv[0], uv[0] + 400])[None]  # slot 0 = track 1, slot 1 = track 0, slot 2 = nobody
    sc = np.full(xy.shape[:-1], 0.9)
    cfg = ExtraJointsConfig()
    assert assign_views(P, X, xy, sc, cfg).tolist() == [[1, 0]]
    X2 = X.copy()
    X2[1] = np.nan  # a track with no known joint takes no view
    assert assign_views(P, X2, xy, sc, cfg).tolist() == [[1, -1]]
    sc[0, 1] = 0.0  # track 0's detection unseen: nothing inside the gate
    assert assign_views(P, X, xy, sc, cfg).tolist() == [[-1, 0]]


def test_attach_joints_checks_shapes_and_bad_skeleton():
    tf = TrackFile.empty(np.arange(3), np.zeros(3, np.int64), 25.0)
    with pytest.raises(ValueError, match="detections of 4 frames"):
        attach_joints(
            tf,
            np.zeros((2, 3, 4)),
            np.zeros((2, 4, 1, 5, 2)),
            np.zeros((2, 4, 1, 5)),
            tuple("abcde"),
            [-1, 0, 0, 0, 0],
        )
    tf19 = TrackFile.empty(np.arange(4), np.zeros(4, np.int64), 25.0)
    with pytest.raises(ValueError, match="shares 0 joints.*greedy tracker"):
        attach_joints(
            tf19,
            np.zeros((2, 3, 4)),
            np.zeros((2, 4, 1, 5, 2)),
            np.zeros((2, 4, 1, 5)),
            tuple("abcde"),
            [-1] * 5,
        )
    with pytest.raises(ValueError, match="'body19', 'whole_body' or a skeleton TOML"):
        ParticleTrackConfig.from_dict({"skeleton": "feet"})


def test_pipeline_gives_the_particle_tracker_the_triangulate_skeleton():
    from roomcap.pipeline.config import PipelineConfig

    wb = {"triangulate": {"options": {"skeleton": "whole_body"}}}
    cfg = PipelineConfig.from_dict({**wb, "track": {"tracker": "particle", "options": {"n_samples": 50}}})
    assert cfg.track.skeleton == "whole_body" and cfg.track.particle.n_samples == 50
    track = {"tracker": "particle", "options": {"skeleton": "body19"}}
    own = PipelineConfig.from_dict({**wb, "track": track})
    assert own.track.skeleton == "body19"  # the track options' own choice wins
    assert PipelineConfig.from_dict({"track": {"tracker": "particle"}}).track == ParticleTrackConfig()
