"""The particle tracker streamed: the streamed stage (track/particle_chunked.py) equals the whole-session
run bit for bit, resumes after a kill from the last complete chunk, and rebuilds damaged parts."""

from __future__ import annotations

import json
import os
import shutil
import sys

import numpy as np
import pytest
from track_helpers import render_kp, ring_P
from triangulate_helpers import TEMPLATE, killed_after_commits

from roomcap.capture.session import SessionLayout
from roomcap.core.errors import FormatError
from roomcap.synthetic.render import RenderConfig, render
from roomcap.synthetic.rigs import kitchen
from roomcap.synthetic.world import SceneConfig, make_scene, write_session
from roomcap.track import particle_chunked as stream
from roomcap.track.greedy import frame_times_s, pause_clock
from roomcap.track.particle import ParticleTracker
from roomcap.track.particle_config import ParticleConfig
from roomcap.track.particle_offline import finish_tracks, gather_estimates, track_sequence
from roomcap.track.stage import track_session_particle
from roomcap.track.trackfile import SMOOTHED, TrackFile
from roomcap.triangulate import chunks as C

PCFG = {"n_samples": 80}  # the GRU prior (its hidden state is part of the resumed state)
STREAM = {**PCFG, "chunk_s": 2.0}


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    rig, room = kitchen(4)
    scene = make_scene(room, SceneConfig(n_people=4, duration_s=12.0, fps=25.0, seed=5, enter_leave=True))
    rd = render(
        scene, rig, RenderConfig(noise_px=3.0, missed_joint_rate=0.15, false_positive_rate=0.1, seed=5)
    )
    root = tmp_path_factory.mktemp("pstream")
    write_session(scene, rd, rig, root)
    track_session_particle(root, PCFG)
    return root, TrackFile.load(SessionLayout(root).tracks)


def _copy(session, tmp_path):
    dst = tmp_path / "s"
    shutil.copytree(session[0], dst)
    return dst


def _same_tracks(a: TrackFile, b: TrackFile) -> None:
    assert np.array_equal(a.track_id, b.track_id) and np.array_equal(a.frame_index, b.frame_index)
    for k in ("xyz_m", "confidence", "std_m", "flags", "t_ns"):
        assert np.array_equal(getattr(a, k), getattr(b, k), equal_nan=True), k


def _stepped_frames(monkeypatch) -> list:
    """The frame numbers ``ParticleTracker.step`` is called with from now on (appended as it runs)."""
    frames: list = []
    real_step = ParticleTracker.step

    def counting(self, kp, sc, frame, *a, **k):
        frames.append(frame)
        return real_step(self, kp, sc, frame, *a, **k)

    monkeypatch.setattr(ParticleTracker, "step", counting)
    return frames


@pytest.mark.parametrize("chunk_s", [2.0, 0.52])  # 6 chunks; 24 chunks shorter than the margin (1.44 s)
def test_streamed_equals_whole_session(session, tmp_path, chunk_s):
    root = _copy(session, tmp_path)
    lay = SessionLayout(root)
    track_session_particle(root, {**PCFG, "chunk_s": chunk_s})
    assert not lay.tracks.exists()
    idx = json.loads((C.parts_dir(lay.tracks) / "index.json").read_text())
    assert idx["complete"] and len(idx["chunks"]) == int(np.ceil(12.0 / chunk_s - 1e-9))
    tf = TrackFile.load(lay.tracks)
    assert tf.n_tracks >= 4  # measured 5 (4 people entering and leaving)
    _same_tracks(tf, session[1])  # bit for bit


def test_killed_run_resumes_from_the_last_chunk_and_equals(session, tmp_path, monkeypatch):
    root = _copy(session, tmp_path)
    lay = SessionLayout(root)
    kill_at = int(np.random.default_rng(24).integers(1, 5))  # parts of the filter pass written before
    with killed_after_commits(monkeypatch, kill_at, stream.RAW_SCHEMA), pytest.raises(KeyboardInterrupt):
        track_session_particle(root, STREAM)  # killed after kill_at filter parts
    with pytest.raises(FormatError, match="incomplete"):
        TrackFile.load(lay.tracks)
    frames = _stepped_frames(monkeypatch)
    track_session_particle(root, STREAM)
    assert frames[0] == 50 * kill_at and len(frames) == 300 - 50 * kill_at  # resumed, nothing stepped twice
    _same_tracks(TrackFile.load(lay.tracks), session[1])
    # killed in the clean-up pass after 2 track parts: the rerun steps no frame and writes the rest
    shutil.rmtree(C.parts_dir(lay.tracks))
    with killed_after_commits(monkeypatch, 2, "tracks"), pytest.raises(KeyboardInterrupt):
        track_session_particle(root, STREAM)
    frames.clear()
    track_session_particle(root, STREAM)
    assert frames == []
    _same_tracks(TrackFile.load(lay.tracks), session[1])


def test_damaged_parts_are_rebuilt_never_trusted(session, tmp_path, monkeypatch):
    root = _copy(session, tmp_path)
    lay = SessionLayout(root)
    track_session_particle(root, STREAM)
    raw = stream.raw_parts_dir(lay)
    p2 = raw / "part_00002.npz"
    p2.write_bytes(p2.read_bytes()[:1000])  # a truncated filter part (its state resumes chunk 3)
    tp = C.parts_dir(lay.tracks) / "part_00004.npz"
    tp.write_bytes(tp.read_bytes()[:100])  # a truncated track part
    with pytest.raises(FormatError, match="part_00004"):
        TrackFile.load(lay.tracks)
    frames = _stepped_frames(monkeypatch)
    track_session_particle(root, STREAM)
    assert frames == list(range(100, 150))  # chunk 2 again, from the state after chunk 1; chunk 3 kept
    _same_tracks(TrackFile.load(lay.tracks), session[1])
    # other settings: another key, nothing reused; a whole-session run replaces the parts
    key0 = json.loads((C.parts_dir(lay.tracks) / "index.json").read_text())["key"]
    frames.clear()
    track_session_particle(root, {**STREAM, "seed": 1})
    assert len(frames) == 300
    assert json.loads((C.parts_dir(lay.tracks) / "index.json").read_text())["key"] != key0
    track_session_particle(root, PCFG)
    assert lay.tracks.exists() and not C.parts_dir(lay.tracks).exists()


def test_state_round_trip_continues_bit_for_bit(tmp_path):
    """state_arrays -> npz -> load_state_arrays on a fresh tracker continues exactly (GRU prior, lost ids)."""
    P = ring_P(3)
    t_s = np.arange(80) / 25.0
    gt = np.stack([TEMPLATE + [x, y, 0] for x, y in ((-0.8, -0.6), (0.7, 0.5))])[None] + (
        t_s[:, None, None, None] * np.array([0.3, 0, 0])
    )
    gt = gt.astype(np.float32)
    gt[20:70, 1] = np.nan  # the second person unseen for 2 s: lost, then back
    kp, sc = render_kp(P, gt, noise_px=1.0, seed=3)
    cfg = ParticleConfig(n_samples=60)
    a = ParticleTracker(P, np.full(3, 1000.0), 25.0, cfg)
    out_a = [a.step(kp[t], sc[t], t) for t in range(80)]
    b = ParticleTracker(P, np.full(3, 1000.0), 25.0, cfg)
    out_b = [b.step(kp[t], sc[t], t) for t in range(50)]
    path = tmp_path / "state.npz"
    np.savez(path, **b.state_arrays())
    assert b.lost  # the state holds a lost identity
    c = ParticleTracker(P, np.full(3, 1000.0), 25.0, cfg)
    with np.load(path, allow_pickle=False) as z:
        c.load_state_arrays(dict(z))
    out_b += [c.step(kp[t], sc[t], t) for t in range(50, 80)]
    for x, y in zip(out_a, out_b, strict=True):
        assert np.array_equal(x.track_id, y.track_id)
        assert np.array_equal(x.xyz_m, y.xyz_m, equal_nan=True) and np.array_equal(x.std_m, y.std_m)
    with pytest.raises(ValueError, match="not a particle tracker state"):
        c.load_state_arrays({"state_meta": np.asarray("{}")})


def test_windowed_clean_up_equals_whole_on_a_paused_irregular_recording():
    """finish_tracks on windows with finish_margin_s equals the whole sequence's: 5 % dropped frames,
    jittered stamps, a 30 s pause with consecutive frame numbers, a person missed around it."""
    rng = np.random.default_rng(0)
    T = 200
    keep = np.sort(rng.choice(int(T * 1.05), T, replace=False))
    t_s = keep / 25.0 + rng.uniform(-0.003, 0.003, T)
    t_s[100:] += 30.0
    t_s = np.sort(t_s) - t_s.min()
    gt = np.stack([TEMPLATE + [x, y, 0] for x, y in ((-0.8, -0.6), (0.7, 0.5))])[None] + (
        t_s[:, None, None, None] * np.array([0.02, 0, 0])
    )
    P = ring_P(3)
    gt = gt.astype(np.float32)
    gt[140:175, 1] = np.nan  # the second person coasts, ends, comes back
    kp, sc = render_kp(P, gt, noise_px=1.0, seed=4)
    kp[95:104], sc[95:104] = np.nan, 0.0
    cfg = ParticleConfig(motion="constant_velocity", n_samples=60)
    tr = ParticleTracker(P, np.full(3, 1000.0), 25.0, cfg)
    t_ns = np.round(t_s * 1e9).astype(np.int64)
    whole = track_sequence(tr, kp, sc, np.arange(T), t_ns=t_ns)
    tr = ParticleTracker(P, np.full(3, 1000.0), 25.0, cfg)
    t_s = frame_times_s(np.arange(T), t_ns, 25.0)
    raw = gather_estimates([tr.step(kp[t], sc[t], t, None, float(t_s[t])) for t in range(T)], 19)
    assert tr.pauses == 1
    counts = raw.seen.sum(0)
    clock, _ = pause_clock(t_s, tr.config.max_gap_s, 25.0)
    margin = stream.finish_margin_s(tr.config, 25.0)
    for a in range(0, T, 17):
        b = min(T, a + 17)
        w0, w1 = stream.window_bounds(clock, a, b, margin)
        win = type(raw)(*(getattr(raw, f)[w0:w1] if f != "track_id" else raw.track_id for f in _FIELDS))
        res = finish_tracks(win, t_s[w0:w1], tr.config, 25.0, evidence_frames=counts)
        assert np.array_equal(res.track_id, whole.track_id)
        assert np.array_equal(res.xyz_m[a - w0 : b - w0], whole.xyz_m[a:b], equal_nan=True), (a, b)
        assert np.array_equal(res.flags[a - w0 : b - w0], whole.flags[a:b])
    assert (whole.flags & SMOOTHED).any() and not np.isfinite(whole.xyz_m[100:104]).any()  # across the pause


_FIELDS = ("track_id", "xyz_m", "std_m", "confidence", "flags", "n_views", "seen")


def _rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc heap")
def test_release_free_memory_returns_the_fragmented_heap():
    """The pattern of the filter's temporaries: once a large mmapped block is freed, glibc serves blocks of
    that size from the heap and keeps them when freed; release_free_memory gives the pages back."""
    from roomcap.core.memory import release_free_memory

    if not release_free_memory():
        pytest.skip("no malloc_trim (not glibc)")
    a = np.ones(30 << 18, np.float32)  # 30 MB, mmapped; freeing it raises glibc's mmap threshold
    del a
    blocks = [np.ones(20 << 18, np.float32) for _ in range(10)]  # 10 x 20 MB, now on the heap
    keep = blocks[-1]
    del blocks
    before = _rss_mb()
    release_free_memory()
    after = _rss_mb()
    assert before - after > 100, (before, after)  # measured 181 MB given back (308 -> 126 MB)
    assert keep[0] == 1.0
