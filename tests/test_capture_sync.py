"""Frame-set grouping: pure function and online Synchroniser agree; timing report finds drift and skew."""

from __future__ import annotations

import numpy as np

from roomcap.capture.sources import Frame
from roomcap.capture.sync import Synchroniser, group_timestamps, timing_report


def _ts(n, fps, offset_ns=0, drift_ppm=0.0, drop=()):
    t = (np.arange(n) * 1e9 / fps * (1 + drift_ppm * 1e-6)).astype(np.int64) + offset_ns
    return np.delete(t, list(drop))


def test_group_timestamps_within_half_a_frame():
    t = {
        "a": _ts(30, 30),
        "b": _ts(30, 30, offset_ns=4_000_000, drop=[10]),
        "c": _ts(30, 30, offset_ns=-3_000_000),
    }
    sets = group_timestamps(t, tolerance_ns=16_666_667)
    assert len(sets) == 30
    assert (sets[:, 1] == -1).sum() == 1 and sets[
        10, 1
    ] == -1  # the dropped frame leaves a hole, nothing shifts
    assert np.array_equal(sets[:, 0], np.arange(30))


def test_online_synchroniser_matches_the_pure_function(rng):
    t = {"a": _ts(60, 30), "b": _ts(60, 30, 5_000_000, drop=[7, 8]), "c": _ts(60, 30, -2_000_000, drop=[30])}
    expect = group_timestamps(t, 16_666_667)
    sync = Synchroniser(list(t), 16_666_667, max_wait_ns=10**12)
    events = sorted(
        (int(ts + rng.integers(0, 3_000_000)), cam, i) for cam, arr in t.items() for i, ts in enumerate(arr)
    )
    got = []
    for host, cam, i in events:  # frames arrive in host order with jitter
        sync.push(cam, Frame(None, int(t[cam][i]), host, i))
        got += sync.pop_ready(host)
    for cam in t:
        sync.push(cam, None)
    got += sync.pop_ready(0, flush=True)
    rows = np.asarray([[fs.frames[c].sequence if fs.frames[c] else -1 for c in t] for fs in got])
    assert np.array_equal(rows, expect)
    assert sync.stats.complete == int((expect >= 0).all(1).sum())


def test_incomplete_set_emitted_after_max_wait():
    sync = Synchroniser(["a", "b"], 10_000_000, max_wait_ns=50_000_000)
    sync.push("a", Frame(None, 0, 1_000, 0))
    assert sync.pop_ready(20_000_000) == []  # b may still come
    out = sync.pop_ready(60_000_000)
    assert len(out) == 1 and out[0].frames["b"] is None and not out[0].complete


def test_timing_report_fps_drops_skew_and_drift(rng):
    n, fps = 900, 30.0
    tabs = {}
    for cam, off, drift in (("a", 0, 0.0), ("b", 3_000_000, 500.0)):
        t_dev = _ts(n, fps, off, drift)
        host = _ts(n, fps) + 20_000_000 + rng.integers(0, 4_000_000, n)  # host clock: arrival with jitter
        seq = np.arange(n)
        keep = np.ones(n, bool)
        if cam == "b":
            keep[[100, 101, 500]] = False
        tabs[cam] = np.stack([np.arange(keep.sum()), t_dev[keep], host[keep], seq[keep]], axis=1)
    r = timing_report(tabs, {"a": fps, "b": fps})
    assert r["cameras"]["b"]["dropped_sequence"] == 3
    assert abs(r["cameras"]["a"]["fps_measured"] - 30) < 0.01
    assert abs(r["cameras"]["b"]["drift_ppm"] - 500) < 100  # measured ~500 (device clock vs host arrival)
    assert abs(r["cameras"]["a"]["drift_ppm"]) < 100
    assert 9.5 < r["skew_ms_median"] < 11.5  # 3 ms offset + 500 ppm x 15 s median = 10.5 ms (measured 10.49)
    assert n - 6 <= r["complete_sets"] <= n - 3  # the last frames drift past the tolerance (measured 896)
