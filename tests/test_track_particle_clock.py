"""The particle filter on the clock: durations on the clock (t_ns), dropped frames, jittered
timestamps and a 30 s pause of the recorder while the frame numbers stay consecutive."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from track_helpers import render_kp, ring_P
from triangulate_helpers import TEMPLATE

from roomcap.track.particle import ParticleTracker
from roomcap.track.particle_config import ParticleConfig
from roomcap.track.particle_offline import track_sequence
from roomcap.track.trackfile import PREDICTED, SMOOTHED
from roomcap.triangulate import evaluate as ev

FOCAL = np.full(3, 1000.0)
FAST = dict(motion="constant_velocity", n_samples=150)


def _two_walkers(t_s: np.ndarray, speed_m_s: float) -> np.ndarray:
    """Two people walking along x at ``speed_m_s``, 1.5 m apart in y: (T,2,J,3) at times t_s (T,)."""
    t = t_s[:, None, None]
    a = TEMPLATE[None] + np.array([-1.0, -0.75, 0]) + t * np.array([speed_m_s, 0, 0])
    b = TEMPLATE[None] + np.array([-1.0, 0.75, 0]) + t * np.array([speed_m_s, 0, 0])
    return np.stack([a, b], 1).astype(np.float32)


def _run(gt, t_s, miss=None, **cfg):
    P = ring_P(3)
    kp, sc = render_kp(P, gt, noise_px=1.0, seed=2)
    if miss is not None:
        kp[miss], sc[miss] = np.nan, 0.0
    tr = ParticleTracker(P, FOCAL, 25.0, ParticleConfig(**{**FAST, **cfg}))
    t_ns = np.round(t_s * 1e9).astype(np.int64)
    return track_sequence(tr, kp, sc, np.arange(len(gt)), t_ns=t_ns), tr


def _per_frame_error(xyz, gt) -> np.ndarray:
    """(T,) error of the track nearest each person, the worse person (NaN where none is output)."""
    d = np.linalg.norm(xyz.astype(np.float64)[:, :, None] - gt[:, None], axis=-1)  # (T,K,P,J)
    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.nanmax(np.nanmin(np.nanmean(d, -1), 1), 1)


@pytest.mark.parametrize(
    "pause_s,speed_m_s,moved", [(30.0, 0.02, "little"), (30.0, 0.1, "far"), (8.0, 0.075, "little")]
)
def test_a_pause_of_the_recorder(pause_s, speed_m_s, moved):
    """Frames 0-59 at 25 Hz, a pause of 30 s (or 8 s), frames 60-119 with consecutive numbers; people walk
    on at 0.02 m/s (0.6 m further after the 30 s pause; 0.6 m after 8 s at 0.075 m/s) or 0.1 m/s (3 m).
    Nobody is detected in frames 58-61."""
    t_s = np.arange(120) / 25.0
    t_s[60:] += pause_s
    gt = _two_walkers(t_s, speed_m_s)
    res, tr = _run(gt, t_s, miss=np.s_[58:62])
    assert tr.pauses == 1 and abs(tr.clock_s - 119 / 25.0) < 1e-6  # the pause counts as one frame
    # nothing output across the pause: frames 58-59 coast before it (no smoothing reaches across it),
    # frames 60-61 would be a guess over 30 unseen seconds
    assert not np.isfinite(res.xyz_m[60:62]).any()
    assert not (res.flags[60:62] & SMOOTHED).any()
    err = _per_frame_error(res.xyz_m, gt)
    near, elsewhere = np.nanmax(err[np.r_[50:58, 62:70]]), np.nanmedian(err)
    assert near < 3.0 * elsewhere and near < 0.03  # measured 2.9 and 6.0 mm against 2.0-2.1 mm
    mot = ev.mot_metrics(gt.astype(np.float64), res.xyz_m.astype(np.float64), threshold_m=0.2)
    if moved == "little":  # identities kept across the pause (0.6 m < the gates + pause_gate_m)
        assert len(res.track_id) == 2 and mot.id_switches == 0
    else:  # 3 m in the pause: new tracks rather than a guess
        assert len(res.track_id) == 4
    # the same with pause_gate_m = 0: the association gate (0.3 m) and re-anchoring no longer reach 0.6 m
    if moved == "little":
        res0, _ = _run(gt, t_s, miss=np.s_[58:62], pause_gate_m=0.0, reid_dist_m=0.1)
        assert len(res0.track_id) > 2


def test_dropped_frames_and_jittered_timestamps():
    """5 % of the frames dropped (rows absent), timestamps jittered by up to 3 ms, walking at 1.2 m/s: the
    prior steps once per missed frame, so the tracks keep up."""
    rng = np.random.default_rng(5)
    keep = np.sort(rng.choice(150, 142, replace=False))
    t_s = keep / 25.0 + rng.uniform(-0.003, 0.003, len(keep))
    gt = _two_walkers(t_s, 1.2)
    res, tr = _run(gt, t_s)
    assert tr.pauses == 0 and len(res.track_id) == 2
    mot = ev.mot_metrics(gt.astype(np.float64), res.xyz_m.astype(np.float64), threshold_m=0.2)
    assert mot.id_switches == 0 and mot.mota > 0.98  # measured 1.0, MPJPE 7.0 mm
    assert ev.mpjpe(gt.astype(np.float64), res.xyz_m.astype(np.float64))["mpjpe_m"] < 0.02


def test_track_death_is_in_seconds_not_frames():
    """At 50 Hz with end_after_s = 0.4, a track without detections ends after 20 frames (0.4 s)."""
    t_s = np.arange(60) / 50.0
    gt = _two_walkers(t_s, 0.5)
    P = ring_P(3)
    kp, sc = render_kp(P, gt, noise_px=1.0, seed=2)
    kp[30:], sc[30:] = np.nan, 0.0
    tr = ParticleTracker(P, FOCAL, 50.0, ParticleConfig(**FAST, end_after_s=0.4, trim_coast=False))
    res = track_sequence(tr, kp, sc, t_ns=np.round(t_s * 1e9).astype(np.int64))
    alive = np.isfinite(res.xyz_m).all(-1).all(-1)  # (T,K)
    assert alive[29:49].all() and not alive[50:].any()
    assert (res.flags[31:49] & PREDICTED).all()


def test_frame_count_keys_and_bad_times():
    cfg = ParticleConfig(smooth_sigma_frames=4.0).at_fps(60.0)
    assert cfg.smooth_sigma_s == 4.0 / 60 and cfg.smooth_sigma_frames is None
    assert ParticleConfig().at_fps(50.0).smooth_sigma_s == 2.0 / 50  # the seed's 2 frames
    assert ParticleConfig(smooth_sigma_s=0.1).at_fps(60.0) == ParticleConfig(smooth_sigma_s=0.1)
    P = ring_P(3)
    tr = ParticleTracker(P, FOCAL, 25.0, ParticleConfig(**FAST))
    kp, sc = np.full((3, 0, 19, 2), np.nan, np.float32), np.zeros((3, 0, 19), np.float32)
    tr.step(kp, sc, 0, t_s=1.0)
    with pytest.raises(ValueError, match="frame 1: time 0.5"):
        tr.step(kp, sc, 1, t_s=0.5)
    with pytest.raises(ValueError, match="frame 7: its timestamp"):
        t_ns = np.arange(10, dtype=np.int64) * 40_000_000
        t_ns[7] = t_ns[6]
        track_sequence(
            ParticleTracker(P, FOCAL, 25.0), np.zeros((10, 3, 0, 19, 2)), np.zeros((10, 3, 0, 19)), t_ns=t_ns
        )


def test_max_people_caps_the_tracks_at_once():
    """A recording of a known number of people: ``max_people`` stops new identities beyond it, set as a user
    would in ``[track.options]`` and checked when the config loads."""
    t_s = np.arange(40) / 25.0
    gt = _two_walkers(t_s, 0.5)
    both, _ = _run(gt, t_s)
    one, _ = _run(gt, t_s, max_people=1)
    assert len(both.track_id) == 2 and len(one.track_id) == 1
    from roomcap.core.errors import FormatError
    from roomcap.pipeline.config import PipelineConfig

    cfg = PipelineConfig.from_dict({"track": {"tracker": "particle", "options": {"max_people": 2}}})
    assert cfg.track.particle.max_people == 2
    with pytest.raises(FormatError, match=r"p.toml: field 'track.options.particle.max_people'.*range"):
        PipelineConfig.from_dict({"track": {"options": {"max_people": -1}}}, "p.toml")
