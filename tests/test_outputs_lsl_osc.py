"""Track streams (track.streams): the live track stage's every frame set to an LSL inlet and an OSC server on
loopback, equal to the live track file; births and deaths as the file has them; `tracks stream` replays a
file at its own clock; consumers that go away never stop the sender; missing packages name the extra.

Network: loopback only. liblsl reads its configuration file from LSLAPICFG (set here, with LSL_API_CFG, to
a file with ResolveScope = machine and KnownPeers 127.0.0.1), so no multicast leaves the machine."""

from __future__ import annotations

import os
import sys
import threading
import time
from types import SimpleNamespace

import numpy as np
import pytest
from track_helpers import walkers

from roomcap.capture.config import parse_config
from roomcap.capture.live import LiveStep
from roomcap.capture.session import SessionLayout
from roomcap.capture.sources import Frame, host_now_ns
from roomcap.capture.sync import FrameSet
from roomcap.keypoints.skeletons import CANONICAL
from roomcap.outputs.lsl_osc import (
    OSC_BIRTH,
    OSC_DEATH,
    OSC_FRAME,
    OSC_PERSON,
    SlotMap,
    StreamConfig,
    StreamError,
    TrackStreamer,
    track_events,
)
from roomcap.pipeline.live import LiveContext, _track
from roomcap.pipeline.live_outputs import StepFeed
from roomcap.synthetic.rigs import ring_rig
from roomcap.track.particle_config import ParticleConfig
from roomcap.track.trackfile import TrackFile

try:
    import pylsl
except ImportError:  # the LSL tests skip; the others run
    pylsl = None
try:
    from pythonosc import dispatcher, osc_server
except ImportError:
    dispatcher = osc_server = None
need_lsl = pytest.mark.skipif(pylsl is None, reason="pylsl not installed: pip install 'roomcap[stream]'")
need_osc = pytest.mark.skipif(
    osc_server is None, reason="python-osc not installed: pip install 'roomcap[stream]'"
)

FAST = ParticleConfig(motion="constant_velocity", n_samples=100)
J = CANONICAL.n_joints


@pytest.fixture(scope="module", autouse=True)
def lsl_loopback(tmp_path_factory):
    cfg = tmp_path_factory.mktemp("lsl") / "lsl_api.cfg"
    cfg.write_text(
        "[ports]\nIPv6 = disable\n[multicast]\nResolveScope = machine\n"
        "[lab]\nKnownPeers = {127.0.0.1}\nSessionID = roomcap-tests\n"
    )
    old = {k: os.environ.get(k) for k in ("LSLAPICFG", "LSL_API_CFG")}
    os.environ["LSLAPICFG"] = os.environ["LSL_API_CFG"] = str(cfg)
    yield cfg
    for k, v in old.items():
        if v is None:
            os.environ.pop(k, None)
        else:
            os.environ[k] = v


class OscSink:
    """An OSC server on 127.0.0.1 (a free port) recording every message in arrival order (one thread)."""

    def __init__(self):
        self.msgs: list[tuple[str, tuple]] = []
        d = dispatcher.Dispatcher()
        d.set_default_handler(lambda addr, *a: self.msgs.append((addr, a)))
        self.server = osc_server.BlockingOSCUDPServer(("127.0.0.1", 0), d)
        self.port = self.server.server_address[1]
        self.thread = threading.Thread(
            target=self.server.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True
        )
        self.thread.start()

    def wait(self, n: int, timeout_s: float = 5.0) -> None:
        t0 = time.monotonic()
        while len(self.msgs) < n and time.monotonic() - t0 < timeout_s:
            time.sleep(0.01)

    def close(self):
        self.server.shutdown()
        self.server.server_close()


def _inlet(source_id: str):
    (info,) = pylsl.resolve_byprop("source_id", source_id, 1, 5.0)
    inlet = pylsl.StreamInlet(info, max_buflen=60)
    inlet.open_stream(5.0)
    return inlet


def _pull_all(inlet, n: int, timeout_s: float = 5.0):
    data, ts = [], []
    t0 = time.monotonic()
    while len(data) < n and time.monotonic() - t0 < timeout_s:
        d, t = inlet.pull_chunk(timeout=0.2)
        data += d
        ts += t
    return data, ts


def _live_steps(rig, X, fps=25.0, gone_after=None):
    """Synthetic frame sets of walkers X (T,P,J,3); person 1 leaves the room after frame ``gone_after``."""
    names = tuple(c.name for c in rig.cameras)
    t0 = host_now_ns()
    for t in range(len(X)):
        t_ns = t0 + int(round(t / fps * 1e9))
        uv = rig.project(X[t].reshape(-1, 3)).reshape(len(names), *X.shape[1:3], 2)
        sc = np.full(uv.shape[:3], 0.9)
        if gone_after is not None and t > gone_after:
            uv[:, 1], sc[:, 1] = np.nan, 0.0
        dets = {n: SimpleNamespace(xy_px=uv[c], score=sc[c], skeleton="body19") for c, n in enumerate(names)}
        fs = FrameSet(t, t_ns, {n: Frame(None, t_ns, t_ns, t) for n in names})
        yield LiveStep(fs, names, {"detections": dets, "final": t == len(X) - 1})


@need_lsl
@need_osc
def test_live_frames_reach_an_lsl_inlet_and_an_osc_server_equal_to_the_live_track_file(tmp_path):
    rig = ring_rig(4, radius_m=4.0)
    names = [c.name for c in rig.cameras]
    cfg = parse_config({"cameras": [{"name": n, "source": "synthetic:", "fps": 25} for n in names]})
    lay = SessionLayout(tmp_path / "S1")
    stage = _track(LiveContext(cfg, lay, rig, FAST, chunk_frames=20))
    osc = OscSink()
    streamer = TrackStreamer(
        StreamConfig(("lsl", "osc"), ("127.0.0.1", osc.port), slots=4, session="S1"), 25.0
    )
    feed = StepFeed(None, streamer)
    data_in, mark_in = _inlet("roomcap-S1"), _inlet("roomcap-S1-events")
    desc = data_in.info().desc()
    assert (
        desc.child("layout").child_value("slots") == "4"
        and desc.child("skeleton").child_value("id") == "body19"
    )
    assert desc.child("channels").child("channel").child_value("label") == "s00_nose_x"
    X = walkers(2, 90, seed=3)
    t_ns = []
    for step in _live_steps(rig, X, gone_after=30):
        stage(step)
        feed(step)  # what capture-run's on_step does after the stages
        t_ns.append(step.frameset.t_ns)
    offset_s = np.median(
        [host_now_ns() / 1e9 - pylsl.local_clock() for _ in range(5)]
    )  # the test's own mapping
    data, ts = _pull_all(data_in, len(t_ns))
    marks, mts = _pull_all(mark_in, 100, timeout_s=1.0)
    streamer.close()
    tf = TrackFile.load(lay.live_tracks)
    assert tf.n_frames == len(data) == len(t_ns) == 90  # every frame set, none lost
    # timestamps: t_ns mapped to LSL's clock, within 1 ms (measured: a few microseconds)
    err_ms = np.abs(np.asarray(ts) - (np.asarray(t_ns) / 1e9 - offset_s)) * 1e3
    assert err_ms.max() < 1.0, err_ms.max()
    # positions: each slot's id channel names the track; its joints equal the file's (float32, bit for bit)
    arr = np.asarray(data, np.float32)
    S = 4
    slot_ids = arr[:, S * J * 4 :]
    xyz = arr[:, : S * J * 4].reshape(-1, S, J, 4)
    present = np.isfinite(tf.xyz_m).all(-1).any(-1)  # (T,K)
    for t in range(tf.n_frames):
        got = {int(i): s for s, i in enumerate(slot_ids[t]) if np.isfinite(i)}
        assert sorted(got) == sorted(tf.track_id[present[t]].tolist())
        for tid, s in got.items():
            k = int(np.flatnonzero(tf.track_id == tid)[0])
            np.testing.assert_array_equal(xyz[t, s, :, :3], tf.xyz_m[t, k])
            np.testing.assert_array_equal(xyz[t, s, :, 3], tf.std_m[t, k])
    # births and deaths: as the file has them, at the frame's timestamp
    want = track_events(present, tf.track_id)
    assert any(e[1] == "death" for e in want), "the person who left should end a track"
    got_ev = [(m[0].split()[0], int(m[0].split()[1])) for m in marks]
    assert got_ev == [(kind, tid) for _, kind, tid in want]
    np.testing.assert_allclose(mts, [ts[t] for t, _, _ in want], atol=1e-6)
    # OSC: the same positions, one /roomcap/person message per person per frame
    n_person = int(present.sum())
    osc.wait(len(t_ns) + n_person + len(want))
    osc.close()
    frames = [a for addr, a in osc.msgs if addr == OSC_FRAME]
    persons = [a for addr, a in osc.msgs if addr == OSC_PERSON]
    assert len(frames) == 90 and len(persons) == n_person
    assert [a[0] for addr, a in osc.msgs if addr == OSC_BIRTH] == [tid for _, k, tid in want if k == "birth"]
    assert [a[0] for addr, a in osc.msgs if addr == OSC_DEATH] == [tid for _, k, tid in want if k == "death"]
    i = 0
    for t in range(tf.n_frames):
        assert frames[t][0] == tf.frame_index[t] and frames[t][2] == present[t].sum()
        assert abs(frames[t][1] - tf.t_ns[t] / 1e9) < 1e-6  # a double: the frame's time to the microsecond
        for k in np.flatnonzero(present[t]):
            pid, *flat = persons[i]
            i += 1
            assert pid == tf.track_id[k]
            np.testing.assert_array_equal(np.asarray(flat, np.float32).reshape(J, 3), tf.xyz_m[t, k])


@need_lsl
@need_osc
def test_an_empty_room_is_a_sample_for_every_frame_set(tmp_path, caplog):
    """Nobody in view: the live track stage gives 0 people; every frame set still reaches LSL (every slot
    NaN) and OSC (a frame message with 0 people), and so does a set without a track estimate at all."""
    rig = ring_rig(2, radius_m=4.0)
    names = [c.name for c in rig.cameras]
    cfg = parse_config({"cameras": [{"name": n, "source": "synthetic:", "fps": 25} for n in names]})
    stage = _track(LiveContext(cfg, SessionLayout(tmp_path / "S2"), rig, FAST, chunk_frames=20))
    osc = OscSink()
    streamer = TrackStreamer(StreamConfig(("lsl", "osc"), ("127.0.0.1", osc.port), slots=2, session="S2"), 25)
    feed = StepFeed(None, streamer)
    data_in = _inlet("roomcap-S2")
    X = np.full((12, 1, J, 3), np.nan)  # nobody: no detection in any view
    with caplog.at_level("WARNING"):
        for i, step in enumerate(_live_steps(rig, X)):
            if i < 10:  # the track stage ran: 0 people
                stage(step)
                assert len(step.outputs["tracks"].track_id) == 0
            feed(step)  # the last two: no track estimate (the stage failed or is off)
        data, _ = _pull_all(data_in, 12)
        osc.wait(12)
    streamer.close()
    osc.close()
    assert len(data) == 12 and np.isnan(np.asarray(data, np.float32)).all()
    frames = [a for addr, a in osc.msgs if addr == OSC_FRAME]
    assert [f[0] for f in frames] == list(range(12)) and all(f[2] == 0 for f in frames)
    assert not [m for addr, m in osc.msgs if addr == OSC_PERSON]
    assert "stream" not in caplog.text and not feed.failed


def _file(T=12, fps=25.0):
    """Two tracks, the second born at frame 3 and gone after frame 8."""
    xyz = np.full((T, 2, J, 3), np.nan, np.float32)
    xyz[:, 0] = np.arange(T, dtype=np.float32)[:, None, None] * 0.01 + 1.0
    xyz[3:9, 1] = 2.0
    return TrackFile(
        fps=fps,
        frame_index=np.arange(T),
        t_ns=10**12 + np.arange(T) * int(1e9 / fps),
        track_id=np.array([5, 9]),
        joint_names=CANONICAL.joint_names,
        parents=np.asarray(CANONICAL.parents),
        xyz_m=xyz,
        confidence=np.ones((T, 2, J), np.float32),
        std_m=np.full((T, 2, J), 0.02, np.float32),
        flags=np.ones((T, 2, J), np.uint8),
        source="test",
    )


@need_osc
def test_tracks_stream_replays_a_file_at_its_own_clock(tmp_path, capsys):
    from roomcap.outputs.cli import main as tracks

    tf = _file()
    path = tmp_path / "tracks.npz"
    tf.save(path)
    osc = OscSink()
    t0 = time.monotonic()
    rc = tracks(["stream", str(path), "--stream", "osc", "--osc-to", f"127.0.0.1:{osc.port}"])
    elapsed = time.monotonic() - t0
    assert rc == 0, capsys.readouterr().err
    osc.wait(12 + 12 + 6 + 3)  # frames, persons, two births and a death: all of them, or close races the last
    osc.close()
    assert elapsed >= 11 / 25 * 0.95  # the file's own pace: 11 frame periods (measured 0.45-0.5 s)
    addrs = [a for a, _ in osc.msgs]
    assert addrs.count(OSC_FRAME) == 12 and addrs.count(OSC_PERSON) == 12 + 6
    assert [a for a, m in osc.msgs if a in (OSC_BIRTH, OSC_DEATH)] == [OSC_BIRTH, OSC_BIRTH, OSC_DEATH]
    assert "streamed 12 frames" in capsys.readouterr().out


@need_lsl
def test_replay_to_lsl_lists_every_slot_and_keeps_the_file_spacing(tmp_path):
    from roomcap.outputs.lsl_osc import replay

    tf = _file()
    slot_ids = {5: 0, 9: 1}
    st = TrackStreamer(StreamConfig(("lsl",), None, slots=2, session="R"), 25.0, slot_ids=slot_ids)
    inlet = _inlet("roomcap-R")
    slots = inlet.info().desc().child("slots")
    listed, e = {}, slots.child("slot")
    while not e.empty():
        listed[int(e.child_value("track_id"))] = int(e.child_value("index"))
        e = e.next_sibling("slot")
    assert listed == slot_ids
    assert replay(tf, st, speed=0) == 12
    data, ts = _pull_all(inlet, 12)
    st.close()
    assert len(data) == 12
    np.testing.assert_allclose(np.diff(ts), 0.04, atol=1e-6)  # the file's spacing, not the send times
    arr = np.asarray(data, np.float32)
    np.testing.assert_array_equal(
        arr[:, 2 * J * 4 + 1], np.where((np.arange(12) >= 3) & (np.arange(12) < 9), 9, np.nan)
    )


@need_osc
def test_a_consumer_that_goes_away_never_stops_the_sender():
    osc = OscSink()
    st = TrackStreamer(StreamConfig(("osc",), ("127.0.0.1", osc.port)), 25.0)
    xyz = np.ones((1, J, 3), np.float32)
    for t in range(5):
        st.push(t, t * 40_000_000, np.array([1]), xyz, np.zeros((1, J)))
    osc.wait(5 + 5 + 1)
    osc.close()  # the listener is gone: UDP to a closed port
    for t in range(5, 200):
        st.push(t, t * 40_000_000, np.array([1]), xyz, np.zeros((1, J)))
    assert st.frames == 200  # every frame handed over; an error, if the OS reports one, is logged once


def test_slots_are_kept_while_a_track_lives_and_freed_at_its_death():
    m = SlotMap(2)
    assert m.update([4, 7]) == ([(4, 0), (7, 1)], [], [])
    assert m.update([7]) == ([], [(4, 0)], [])
    assert m.update([7, 8, 9]) == ([(8, 0), (9, -1)], [], [9])  # no slot left: 9 goes over OSC only
    assert m.update([8, 4]) == ([(4, 1)], [(7, 1), (9, -1)], [])


def test_missing_packages_and_bad_options_say_what_to_do(monkeypatch, tmp_path, capsys):
    from roomcap.outputs.cli import main as tracks
    from roomcap.outputs.lsl_osc import parse_host_port, parse_kinds

    monkeypatch.setitem(sys.modules, "pylsl", None)  # import pylsl raises ImportError
    with pytest.raises(StreamError, match=r"pip install 'roomcap\[stream\]'"):
        TrackStreamer(StreamConfig(("lsl",)), 25.0)
    _file().save(tmp_path / "t.npz")
    assert tracks(["stream", str(tmp_path / "t.npz"), "--stream", "lsl"]) == 2
    assert "roomcap[stream]" in capsys.readouterr().err
    with pytest.raises(ValueError, match="--osc-to HOST:PORT"):
        StreamConfig(("osc",))
    with pytest.raises(ValueError, match="lsl, osc"):
        parse_kinds(["lsl,zmq"])
    with pytest.raises(ValueError, match="HOST:PORT"):
        parse_host_port("localhost")


@need_lsl
def test_a_file_with_many_tracks_gets_as_many_slots_as_are_present_at_once(tmp_path):
    """70 short tracks, at most 2 at once: 2 slots given at each birth (the layout stays small)."""
    from roomcap.outputs.cli import main as tracks

    T, K = 70, 70
    xyz = np.full((T, K, J, 3), np.nan, np.float32)
    for k in range(K):
        xyz[k, k] = 1.0
        xyz[min(T - 1, k + 1), k] = 1.0  # each track lives two frames: two at once
    tf = TrackFile(
        fps=100.0,
        frame_index=np.arange(T),
        t_ns=np.arange(T) * 10_000_000,
        track_id=np.arange(K) + 100,
        joint_names=CANONICAL.joint_names,
        parents=np.asarray(CANONICAL.parents),
        xyz_m=xyz,
        confidence=np.ones((T, K, J), np.float32),
        std_m=np.full((T, K, J), 0.02, np.float32),
        flags=np.ones((T, K, J), np.uint8),
        source="test",
    )
    tf.save(tmp_path / "many.npz")
    got = {}

    def read():
        inlet = _inlet("roomcap-many")
        got["slots"] = inlet.info().desc().child("layout").child_value("slots")
        got["data"], _ = _pull_all(inlet, T)

    t = threading.Thread(target=read)
    t.start()
    assert tracks(["stream", str(tmp_path / "many.npz"), "--stream", "lsl", "--wait", "2.0"]) == 0
    t.join(10)
    assert got["slots"] == "2"
    ids = np.asarray(got["data"], np.float32)[:, 2 * J * 4 :]
    assert len(ids) == T and all(
        set(r[np.isfinite(r)].astype(int)) == {100 + t} | ({99 + t} if t else set())
        for t, r in enumerate(ids)
    )


@need_lsl
@need_osc
def test_a_track_with_hands_streams_its_hand_joints():
    """A whole-body track (body19 and both hands): the LSL sample grows to 61 joints per slot (the hand
    channels labelled with their COCO-WholeBody names, the hands listed in the description), OSC sends
    the body as before and each seen hand as ``/roomcap/hand``; a frame with the right hand unseen sends
    the left one only."""
    from hands_helpers import SK, wholebody_trackfile, wholebody_xyz

    from roomcap.keypoints.skeletons import HANDS
    from roomcap.outputs.lsl_osc import OSC_HAND, replay

    xyz = wholebody_xyz(1, 6).astype(np.float32)
    right = [SK.index(n) for n in HANDS[21:]]
    xyz[3:, 0, right] = np.nan
    tf = wholebody_trackfile(xyz)
    osc = OscSink()
    cfg = StreamConfig(("lsl", "osc"), ("127.0.0.1", osc.port), slots=1, session="H")
    st = TrackStreamer(cfg, 25.0, tf.joint_names, tuple(int(p) for p in tf.parents), {3: 0})
    inlet = _inlet("roomcap-H")
    info = inlet.info()
    Jw = SK.n_joints
    assert Jw == 61 and info.channel_count() == Jw * 4 + 1
    desc = info.desc()
    assert desc.child("skeleton").child_value("id") == "body19_hands"
    assert desc.child("skeleton").child_value("hands").split(",") == list(HANDS)
    ch, labels = desc.child("channels").child("channel"), []
    while not ch.empty():
        labels.append(ch.child_value("label"))
        ch = ch.next_sibling("channel")
    k = SK.index("left_middle_finger3")
    assert labels[k * 4 : k * 4 + 4] == [f"s00_left_middle_finger3_{c}" for c in ("x", "y", "z", "std")]
    assert replay(tf, st, speed=0) == 6
    data, _ = _pull_all(inlet, 6)
    st.close()
    osc.wait(6 * 2 + 3 * 2 + 3 + 1)  # frames, persons, hands (2 + 2 + 2 + 1 + 1 + 1), the birth
    osc.close()
    arr = np.asarray(data, np.float32)[:, : Jw * 4].reshape(6, Jw, 4)
    np.testing.assert_allclose(arr[..., :3], xyz[:, 0], atol=1e-6)
    persons = [m for a, m in osc.msgs if a == OSC_PERSON]
    assert len(persons) == 6 and all(len(m) == 1 + 19 * 3 for m in persons)
    np.testing.assert_allclose(np.asarray(persons[2][1:]).reshape(19, 3), xyz[2, 0, :19], atol=1e-6)
    hands = [m for a, m in osc.msgs if a == OSC_HAND]
    assert [m[1] for m in hands] == ["left", "right"] * 3 + ["left"] * 3
    assert all(m[0] == 3 and len(m) == 2 + 21 * 3 for m in hands)
    np.testing.assert_allclose(np.asarray(hands[1][2:]).reshape(21, 3), xyz[0, 0, right], atol=1e-6)
