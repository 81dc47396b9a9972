"""The filter's confidence-map + PAF observation (eq. 5.8) on maps rendered from a synthetic person."""

from __future__ import annotations

import numpy as np
import pytest
from track_helpers import render_kp, render_maps, ring_P, walkers

from roomcap.track import observation as obs
from roomcap.track.particle import ParticleTracker
from roomcap.track.particle_config import ParticleConfig
from roomcap.track.particle_offline import track_sequence

FOCAL = np.full(3, 1000.0)
FAST = dict(motion="constant_velocity", n_samples=150, smooth_sigma_frames=0.0)


@pytest.fixture(scope="module")
def scene():
    P = ring_P(3)
    X = walkers(1, 30, seed=5)
    kp, sc = render_kp(P, X, noise_px=1.0, seed=2)
    maps = [render_maps(P, X[t]) for t in range(len(X))]
    return P, X, kp, sc, maps


def test_map_scores_peak_at_the_person(scene):
    P, X, _, _, maps = scene
    offsets = np.float32([0.0, 0.03, 0.08, 0.3])
    S = (X[0, 0][None] + offsets[:, None, None] * np.float32([1, 0.5, 0]))[None]  # (1,4,J,3)
    phi = obs.map_limb_scores(S, P[0], maps[0][0])  # (1,L,4)
    assert phi.shape == (1, 19, 4)
    m = phi[0].mean(0)
    assert m[0] > 0.5  # measured 0.72 (bilinear on 1-px-wide rendered fields)
    assert np.all(np.diff(m) < 0) and m[-1] < 0.05  # falls off with the distance


def test_filter_uses_the_maps_and_tracks(scene):
    P, X, kp, sc, maps = scene
    tr = ParticleTracker(P, FOCAL, 25.0, ParticleConfig(**FAST))
    res = track_sequence(tr, kp, sc, maps_at=lambda t: maps[t])
    assert tr.n_map_scores == len(X) - 1  # every update after the birth frame weighed by the maps
    assert len(res.track_id) == 1 and np.isfinite(res.xyz_m).all()
    err = np.linalg.norm(res.xyz_m[:, 0] - X[:, 0], axis=-1)
    assert np.nanmean(err) < 0.03  # measured 0.0048 m (keypoints only: 0.0049 m)
    ref = ParticleTracker(P, FOCAL, 25.0, ParticleConfig(**FAST))
    track_sequence(ref, kp, sc)
    assert ref.n_map_scores == 0  # keypoints only without maps


def test_maps_carry_a_camera_without_keypoints(scene):
    """Camera 2 loses its keypoints: with its maps it still weighs the samples (eq. 5.8 per camera)."""
    P, X, kp, sc, maps = scene
    kp, sc = kp.copy(), sc.copy()
    kp[5:, 2], sc[5:, 2] = np.nan, 0.0
    tr = ParticleTracker(P, FOCAL, 25.0, ParticleConfig(**FAST))
    res = track_sequence(tr, kp, sc, maps_at=lambda t: maps[t])
    err = np.linalg.norm(res.xyz_m[:, 0] - X[:, 0], axis=-1)
    assert np.nanmean(err) < 0.04  # measured 0.0061 m


def test_maps_must_match_the_cameras(scene):
    P, X, kp, sc, maps = scene
    tr = ParticleTracker(P, FOCAL, 25.0, ParticleConfig(**FAST))
    with pytest.raises(ValueError, match="one entry"):
        tr.step(kp[0], sc[0], 0, maps[0][:2])


@pytest.mark.slow
def test_stage_reads_stored_maps_of_distorted_cameras(tmp_path, caplog):
    """Maps stored the way the keypoints stage stores them (``maps_f16`` raw OpenPose channel layout,
    ``maps_to_img``) are read back in the tracker's layout and weigh the samples; lens distortion applied."""
    import logging

    from roomcap.keypoints.decoders import OPENPOSE_LIMBS
    from roomcap.keypoints.detections import Detections
    from roomcap.keypoints.registry import get_spec
    from roomcap.keypoints.skeletons import CANONICAL, get_skeleton
    from roomcap.synthetic.render import RenderConfig, render
    from roomcap.synthetic.rigs import ring_rig, ring_room
    from roomcap.synthetic.world import SceneConfig, make_scene, write_session
    from roomcap.track.particle_io import load_maps
    from roomcap.track.stage import track_session_particle
    from roomcap.track.trackfile import TrackFile
    from roomcap.triangulate.multiview import load_detections

    rig = ring_rig(3, radius_m=4.0, distortion=True, seed=1)
    scene = make_scene(
        ring_room(3.0), SceneConfig(n_people=1, duration_s=1.2, fps=25.0, seed=2, motion="procedural")
    )
    write_session(scene, render(scene, rig, RenderConfig(seed=2, noise_px=1.0)), rig, tmp_path)
    gt = scene.gt_xyz_m.astype(np.float32)  # (T,1,J,3)
    T, stride = len(gt), 8
    dec = get_spec("openpose_mobilenetv2").decoder
    n = dec.n_parts
    coco = [CANONICAL.index(nm) for nm in get_skeleton("coco18").joint_names]
    P = np.stack([c.P for c in rig.cameras])
    rendered = []
    for ci, cam in enumerate(rig.cameras):
        raw = []
        for t in range(T):
            uv = np.stack([c.project(gt[t, 0]) for c in rig.cameras])[:, None]  # (C,1,J,2) distorted px
            m = render_maps(P, gt[t], cam.size_wh, stride, uv_px=uv)[ci]
            r = np.zeros((m.heat.shape[1], m.heat.shape[2], n + 1 + 2 * len(OPENPOSE_LIMBS)), np.float32)
            r[..., :n] = m.heat[coco].transpose(1, 2, 0)
            for li, (cx, cy) in enumerate(dec.paf_channels):  # the model's own PAF channel order
                r[..., n + 1 + cx], r[..., n + 1 + cy] = m.paf[li, 0], m.paf[li, 1]
            raw.append(r)
            if t == 3:
                rendered.append(m)
        p = tmp_path / "keypoints" / f"{cam.name}.npz"
        d = Detections.load(p)
        Detections(
            d.camera,
            d.skeleton,
            d.frame_index,
            d.t_ns,
            d.xy_px,
            d.score,
            d.boxes,
            "openpose_mobilenetv2",
            d.model_sha256,
            d.image_size_wh,
            extra={
                "maps_f16": np.stack(raw).astype(np.float16),
                "maps_to_img": np.tile(np.float64([[stride, 0, 0], [0, stride, 0]]), (T, 1, 1)),
            },
        ).save(p)
    from roomcap.capture.session import SessionLayout

    sub, mv = load_detections(SessionLayout(tmp_path), rig)
    got = load_maps(SessionLayout(tmp_path), sub, mv.frame_index)(3)
    for g, r in zip(got, rendered, strict=True):
        assert np.abs(g.heat - r.heat).max() < 2e-3 and np.abs(g.paf - r.paf).max() < 2e-3
        assert np.allclose(g.img_to_map, r.img_to_map) and g.distort is not None
    # the distortion maps the undistorted projection onto the image point
    uv_u = sub[0].undistort_px(sub[0].project(gt[3, 0]))
    assert np.abs(got[0].distort(uv_u.astype(np.float32)) - sub[0].project(gt[3, 0])).max() < 0.05
    with caplog.at_level(logging.INFO, logger="roomcap.track.stage"):
        tf = TrackFile.load(
            track_session_particle(tmp_path, {"motion": "constant_velocity", "n_samples": 150})
        )
    assert "confidence maps" in caplog.text
    assert tf.n_tracks == 1
    err = np.nanmean(np.linalg.norm(tf.xyz_m[:, 0] - gt[:, 0], axis=-1))
    assert err < 0.04  # measured 0.012 m (1 px noise, distorted cameras)
