"""Offline sync from 2D keypoint speeds: Pose2Sim known shifts, synthetic-world offsets and drift."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import need_shared

from roomcap.capture.offline_sync import (
    estimate_lag,
    estimate_offsets,
    keypoint_speed,
    read_openpose_folder,
    sync_session,
)
from roomcap.core.fileio import load_toml

CAMS = ("cam01", "cam02", "cam03", "cam04")


def _shift(sig: np.ndarray, k: int) -> np.ndarray:
    """Camera started k frames late (k > 0: its first k frames are missing) or early (k < 0)."""
    if k > 0:
        return sig[k:]
    return np.concatenate([np.full((-k,) + sig.shape[1:], np.nan), sig]) if k < 0 else sig


def test_lag_of_a_shifted_signal_is_exact(rng):
    x = np.convolve(rng.normal(size=400), np.ones(5) / 5, "same")
    for k in (-12, -1, 0, 3, 7):
        est = estimate_lag(x, _shift(x, k), max_lag=20)
        assert est.lag_int == k and abs(est.offset_frames - k) < 0.05


@pytest.mark.parametrize(
    "trial",
    [
        "S00_P01_MultiParticipants/S00_P01_T02_Participants1-2",
        "S00_P00_SingleParticipant/S00_P00_T01_BalancingTrial",
    ],
)
def test_pose2sim_known_shifts_are_recovered_exactly(trial):
    root = need_shared("data", "pose2sim", "session-2024", *trial.split("/"), "pose")
    sig = {c: keypoint_speed(read_openpose_folder(root / f"{c}_json")[0]) for c in CAMS}
    base = estimate_offsets(sig, 60.0, "cam01", max_lag_s=0.5)["cameras"]
    for shifts in ({"cam02": 7, "cam03": -12}, {"cam02": -12, "cam04": 7}):
        shifted = {c: _shift(s, shifts.get(c, 0)) for c, s in sig.items()}
        got = estimate_offsets(shifted, 60.0, "cam01", max_lag_s=0.5)["cameras"]
        for c in CAMS:
            rel = got[c]["offset_frames"] - base[c]["offset_frames"]
            assert round(rel) == shifts.get(c, 0)  # measured within 0.25 frame of +7 / -12
    # the unshifted recordings themselves agree to about a frame (measured -1.2..+0.9 at 60 fps)
    assert all(abs(b["offset_frames"]) < 2 for b in base.values())


def test_synthetic_world_offsets_and_drift_within_one_frame():
    from roomcap.synthetic import RenderConfig, SceneConfig, make_scene, render_scene, ring_rig, ring_room

    rig = ring_rig(4, 3.0)
    scene = make_scene(ring_room(3.0), SceneConfig(n_people=3, duration_s=24, fps=25, seed=3))
    off = (0.0, 3.4, -7.2, 11.6)
    drift = (0.0, 300.0, -200.0, 150.0)  # ppm: at most 0.18 frames over the clip
    r = render_scene(
        scene,
        rig,
        RenderConfig(
            noise_px=2.0, missed_joint_rate=0.1, time_offsets_frames=off, time_drifts_ppm=drift, seed=3
        ),
    )
    sig = {d.camera: keypoint_speed(d.xy_px) for d in r.detections}
    res = estimate_offsets(sig, 25.0, r.detections[0].camera, max_lag_s=1.0, drift=True, window_s=8.0)
    for c, d in enumerate(r.detections):
        est = res["cameras"][d.camera]["offset_frames"]
        assert abs(est - (off[c] - off[0])) < 1.0  # measured errors <= 0.35 frame


def test_sync_session_writes_session_toml(tmp_path):
    from roomcap.keypoints.detections import Detections

    rng = np.random.default_rng(1)
    T, J = 300, 19
    path = np.cumsum(rng.normal(0, 3, (T + 20, 1, J, 2)), axis=0) + 500
    for cam, k in (("a", 0), ("b", 5)):
        xy = path[k : k + T].astype(np.float32)
        Detections(
            camera=cam,
            skeleton="body19",
            frame_index=np.arange(T),
            t_ns=(np.arange(T) * 40_000_000).astype(np.int64),
            xy_px=xy,
            score=np.ones((T, 1, J), np.float32),
            boxes=np.full((T, 1, 5), np.nan, np.float32),
        ).save(tmp_path / "keypoints" / f"{cam}.npz")
    res = sync_session(tmp_path, load_keypoints=Detections.load)
    assert round(res["cameras"]["b"]["offset_frames"]) == 5
    meta = load_toml(tmp_path / "session.toml")
    assert meta["schema"] == "session/1" and meta["sync"]["reference"] == "a"
    assert meta["sync"]["cameras"]["b"]["offset_ns"] == pytest.approx(200_000_000, abs=10_000_000)


def _write_av(path, audio, sr=16000, fps=25, seconds=4.0):
    av = pytest.importorskip("av")
    with av.open(str(path), "w") as c:
        vs = c.add_stream("mpeg4", rate=fps)
        vs.width, vs.height, vs.pix_fmt = 32, 32, "yuv420p"
        aus = c.add_stream("pcm_s16le", rate=sr, layout="mono")
        for _ in range(int(seconds * fps)):
            for p in vs.encode(av.VideoFrame.from_ndarray(np.zeros((32, 32, 3), np.uint8), format="rgb24")):
                c.mux(p)
        for p in vs.encode(None):
            c.mux(p)
        pcm = (np.clip(audio, -1, 1) * 32000).astype(np.int16)
        for k in range(0, len(pcm), 1024):
            fr = av.AudioFrame.from_ndarray(pcm[None, k : k + 1024], format="s16", layout="mono")
            fr.sample_rate, fr.pts = sr, k
            for p in aus.encode(fr):
                c.mux(p)
        for p in aus.encode(None):
            c.mux(p)


def test_audio_sync_recovers_a_known_offset(tmp_path):
    from roomcap.capture.cli import main

    rng = np.random.default_rng(2)
    sr = 16000
    world = np.zeros(sr * 6)  # claps and speech-like bursts at random times
    for t in rng.uniform(0.2, 5.5, 14):
        n = int(rng.uniform(0.02, 0.2) * sr)
        i = int(t * sr)
        world[i : i + n] += rng.normal(0, 0.3, len(world[i : i + n])) * np.hanning(len(world[i : i + n]))
    _write_av(tmp_path / "a.mkv", world[: 4 * sr])
    _write_av(tmp_path / "b.mkv", world[int(0.3 * sr) : int(0.3 * sr) + 4 * sr])  # b started 0.3 s later
    rc = main(["sync", str(tmp_path), "--audio", f"a={tmp_path / 'a.mkv'}", f"b={tmp_path / 'b.mkv'}"])
    assert rc == 0
    off = load_toml(tmp_path / "session.toml")["sync"]["cameras"]["b"]["offset_s"]
    assert abs(off - 0.3) < 0.002  # b's t=0 is a's t=0.3 s (measured error < 1 ms)


def test_trust_says_when_an_offset_is_ambiguous_or_unsupported(rng):
    x = np.convolve(rng.normal(size=400), np.ones(5) / 5, "same")
    good = estimate_lag(x, _shift(x, 4), max_lag=30)
    assert good.trust == "good" and good.peak_ratio > 2
    # a periodic motion (someone pacing at a fixed rate) matches at every period: ambiguous
    t = np.arange(400)
    periodic = np.sin(2 * np.pi * t / 12) + 0.05 * rng.normal(size=400)
    amb = estimate_lag(periodic, _shift(periodic, 4), max_lag=30)
    assert amb.trust == "poor" and amb.peak_ratio < 1.3
    # two unrelated signals: a peak somewhere, but nothing to trust
    noise = estimate_lag(rng.normal(size=400), rng.normal(size=400), max_lag=30)
    assert noise.trust == "poor"
    res = estimate_offsets({"a": x, "b": _shift(x, 4), "c": rng.normal(size=400)}, 25.0, "a", max_lag_s=1.0)
    assert res["cameras"]["a"]["trust"] == "reference"
    assert res["cameras"]["b"]["trust"] == "good" and res["cameras"]["c"]["trust"] == "poor"
