"""Tracks as network streams: every frame's people to the Lab Streaming Layer and to OSC, live or replayed.

``capture-run --live --stream lsl,osc`` sends each frame set's tracks as the live tracker makes them;
``tracks stream SESSION`` replays a recorded track file at its own clock. Both go through
:class:`TrackStreamer`, fed one frame at a time (:meth:`TrackStreamer.push`).

**LSL** (``pylsl``, which ships liblsl; ``pip install 'roomcap[stream]'``). One data outlet per session:

- name ``<name>`` (default ``roomcap``), type ``MoCap``, ``float32``, nominal rate = the capture rate,
  ``source_id`` = ``roomcap-<session>`` (an inlet that reconnects finds the same stream);
- a fixed channel layout of ``S`` slots (``--slots``, default 16) × ``J`` joints (19, ``body19``; a
  whole-body track's own joints, hands included: 61 for ``body19_hands``) ×
  (x_m, y_m, z_m, std_m), slot-major (channel ``(s*J + j)*4 + c``), then ``S`` channels holding each
  slot's track id (NaN = the slot is empty); an absent joint or slot is NaN. World frame: metres, z up
  (the track file's). ``std_m``: the per-joint positional standard deviation (the particle spread);
- timestamps: the frame set's ``t_ns`` (host ``CLOCK_MONOTONIC`` + a fixed offset to UNIX time,
  ``capture.sources.host_now_ns``) mapped to LSL's ``local_clock()`` by an offset measured when the
  outlet opens (``lsl_s = (t_ns - offset_ns) / 1e9``), so EEG, eye trackers and force plates recorded
  through LSL line up with the video frames. A replay maps the file's first frame to the time it starts;
- the stream's XML description (``desc``): ``channels`` (label, type ``PositionX|Y|Z`` or ``StdDev``,
  unit ``meters``, slot, joint: the LSL mocap meta-data convention), ``layout`` (slots, joints,
  fields, order, units), ``skeleton`` (``body19`` joint names and parents), ``slots`` (slot → track id
  where known when the outlet opens: every one for a replay; live tracks are born later, their slot is
  in the id channels and the markers) and ``clock``.

A second outlet, ``<name>-events`` (type ``Markers``, one ``string`` channel, irregular rate), carries
``birth <track id> slot <s>`` and ``death <track id> slot <s>`` at the frame where a track appears (has
a joint) or disappears. A track keeps its slot while it lives; a slot is freed at its death; more live
tracks than slots are sent over OSC only (warned once).

**OSC** (``python-osc``; UDP to ``--osc-to HOST:PORT``). Per frame, as separate messages:

- ``/roomcap/frame``  ``frame_index:int32, t_s:double, n_people:int32`` (``t_s``: ``t_ns`` / 1e9, UNIX
  seconds of the host clock; a 64-bit double, OSC type ``d``, as a float32 would be 128 s coarse);
- ``/roomcap/person`` ``track_id:int, x0, y0, z0, x1, ... x18, y18, z18`` (float32, metres, z up,
  ``body19`` joint order, or the track's joints without the hands; NaN = joint unknown), one message per
  person present;
- ``/roomcap/hand`` ``track_id:int, side:str ("left" | "right"), x0, y0, z0, ... x20, y20, z20`` (the 21
  hand joints in MediaPipe's landmark order, COCO-WholeBody's ``<side>_hand_root``, ``<side>_thumb1`` ...
  ``<side>_pinky_finger4``), one message per hand with a known joint, only for a track with hands;
- ``/roomcap/birth`` and ``/roomcap/death`` ``track_id:int`` when a track appears or disappears.

A consumer that disappears (an OSC port with no listener, an LSL inlet closed) is logged once and the
stream goes on: UDP and LSL outlets never wait for a reader.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from roomcap.capture.sources import host_now_ns
from roomcap.core.errors import InputError, RoomcapError
from roomcap.keypoints.skeletons import CANONICAL, HAND_LEFT, HAND_RIGHT, HANDS, SKELETONS
from roomcap.track.trackfile import TrackFile

log = logging.getLogger(__name__)

STREAM_KINDS = ("lsl", "osc")
FIELDS = ("x_m", "y_m", "z_m", "std_m")
OSC_FRAME, OSC_PERSON, OSC_BIRTH, OSC_DEATH, OSC_HAND = (
    "/roomcap/frame",
    "/roomcap/person",
    "/roomcap/birth",
    "/roomcap/death",
    "/roomcap/hand",
)
CLOSE_GRACE_S = 0.5  # on close, time for connected LSL inlets to receive the last samples
EXTRA = {"lsl": "stream", "osc": "stream", "rerun": "rerun"}  # pip extra that installs each consumer
_PACKAGE = {"lsl": "pylsl", "osc": "python-osc", "rerun": "rerun-sdk"}


class StreamError(RoomcapError, RuntimeError):
    """A stream cannot be opened (a package missing, a bad address)."""


def missing_package(kind: str) -> StreamError:
    """The error for an optional consumer whose package is not installed, naming the extra."""
    return StreamError(
        f"--stream {kind} needs the {_PACKAGE[kind]} package, which is not installed: "
        f"pip install 'roomcap[{EXTRA[kind]}]' (or pip install {_PACKAGE[kind]})."
    )


def parse_kinds(values: Iterable[str] | None) -> tuple[str, ...]:
    """``--stream lsl,osc`` (repeatable) -> ('lsl', 'osc'), in the order given, each once.

    >>> parse_kinds(["lsl", "osc,lsl"])
    ('lsl', 'osc')
    """
    out: list[str] = []
    for v in values or ():
        for k in (x.strip().lower() for x in v.split(",")):
            if not k:
                continue
            if k not in STREAM_KINDS:
                raise InputError(f"--stream takes {', '.join(STREAM_KINDS)} (comma-separated), got {k!r}.")
            if k not in out:
                out.append(k)
    return tuple(out)


def parse_host_port(text: str, what: str = "--osc-to") -> tuple[str, int]:
    """``HOST:PORT`` -> (host, port).

    >>> parse_host_port("127.0.0.1:9000")
    ('127.0.0.1', 9000)
    """
    host, sep, port = str(text).rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise InputError(f"{what} takes HOST:PORT (e.g. 127.0.0.1:9000), got {text!r}.")
    return host.strip("[]"), int(port)


@dataclass(frozen=True)
class StreamConfig:
    """What to stream and where. ``kinds``: ('lsl', 'osc'); ``osc_to``: (host, port) for OSC;
    ``slots``: LSL person slots; ``name``: the LSL stream name; ``session``: goes into the source id."""

    kinds: tuple[str, ...] = ()
    osc_to: tuple[str, int] | None = None
    slots: int = 16
    name: str = "roomcap"
    session: str = "session"

    def __post_init__(self) -> None:
        bad = [k for k in self.kinds if k not in STREAM_KINDS]
        if bad:
            raise InputError(f"unknown stream kind(s) {bad}; valid: {', '.join(STREAM_KINDS)}.")
        if "osc" in self.kinds and self.osc_to is None:
            raise InputError("--stream osc needs --osc-to HOST:PORT (e.g. --osc-to 127.0.0.1:9000).")
        if not 1 <= int(self.slots) <= 256:
            raise InputError(f"--slots must be 1..256, got {self.slots}.")


def _present(xyz_m: np.ndarray) -> np.ndarray:
    """(K,J,3) -> (K,) bool: the track has at least one known joint this frame (the track file's rule)."""
    return np.isfinite(xyz_m).all(-1).any(-1) if xyz_m.size else np.zeros(len(xyz_m), bool)


class SlotMap:
    """Track id -> LSL slot. A track keeps its slot while present; a slot is freed at the track's death;
    the lowest free slot is given at a birth (a reborn id gets its old slot back when free)."""

    def __init__(self, n_slots: int):
        self.n = int(n_slots)
        self.slot: dict[int, int] = {}
        self.last: dict[int, int] = {}

    def update(self, ids: Sequence[int]) -> tuple[list[tuple[int, int]], list[tuple[int, int]], list[int]]:
        """Present ids of this frame -> (births [(id, slot)], deaths [(id, slot)], ids without a slot);
        slot -1 where none was free."""
        now = [int(i) for i in ids]
        deaths = [(i, s) for i, s in self.slot.items() if i not in set(now)]
        for i, s in deaths:
            del self.slot[i]
            if s >= 0:
                self.last[i] = s
        births = []
        for i in now:
            if i in self.slot:
                continue
            taken = set(self.slot.values())
            old = self.last.get(i)
            s = (
                old
                if old is not None and old not in taken
                else next((k for k in range(self.n) if k not in taken), -1)
            )
            self.slot[i] = s
            births.append((i, s))
        return births, deaths, [i for i in now if self.slot[i] < 0]


def lsl_clock_offset_ns(local_clock: Callable[[], float], n: int = 7) -> int:
    """``host_now_ns() - local_clock()`` in ns, the reading with the shortest bracket of ``n``."""
    best = None
    for _ in range(n):
        a = host_now_ns()
        c = local_clock()
        b = host_now_ns()
        if best is None or b - a < best[0]:
            best = (b - a, (a + b) // 2 - int(round(c * 1e9)))
    assert best is not None
    return best[1]


def _frame_message(frame_index: int, t_ns: int, n_people: int) -> Any:
    """``/roomcap/frame`` with ``t_s`` as a 64-bit double: a float32 of UNIX seconds would be 128 s coarse."""
    from pythonosc.osc_message_builder import OscMessageBuilder  # lazy: the stream extra

    b = OscMessageBuilder(address=OSC_FRAME)
    b.add_arg(frame_index, OscMessageBuilder.ARG_TYPE_INT)
    b.add_arg(t_ns / 1e9, OscMessageBuilder.ARG_TYPE_DOUBLE)
    b.add_arg(n_people, OscMessageBuilder.ARG_TYPE_INT)
    return b.build()


def _lsl() -> Any:
    try:
        import pylsl  # lazy: loads liblsl (the stream extra)
    except ImportError:
        raise missing_package("lsl") from None
    return pylsl


def _osc() -> Any:
    try:
        from pythonosc import udp_client  # lazy: the stream extra
    except ImportError:
        raise missing_package("osc") from None
    return udp_client


class _LslOutlets:
    def __init__(
        self,
        cfg: StreamConfig,
        fps: float,
        joint_names: Sequence[str],
        parents: Sequence[int],
        slot_ids: dict[int, int] | None,
    ):
        pylsl = _lsl()
        self.pylsl = pylsl
        J, S = len(joint_names), cfg.slots
        self.J, self.S = J, S
        sid = f"roomcap-{cfg.session}"
        info = pylsl.StreamInfo(cfg.name, "MoCap", S * J * 4 + S, float(fps), pylsl.cf_float32, sid)
        d = info.desc()
        d.append_child("acquisition").append_child_value("manufacturer", "roomcap").append_child_value(
            "model", "multi-camera markerless tracking (particle filter)"
        )
        chans = d.append_child("channels")
        kinds = ("PositionX", "PositionY", "PositionZ", "StdDev")
        for s in range(S):
            for jn in joint_names:
                for c, f in enumerate(FIELDS):
                    ch = chans.append_child("channel")
                    ch.append_child_value("label", f"s{s:02d}_{jn}_{f[0] if c < 3 else 'std'}")
                    ch.append_child_value("marker", jn)
                    ch.append_child_value("type", kinds[c])
                    ch.append_child_value("unit", "meters")
                    ch.append_child_value("slot", str(s))
        for s in range(S):
            ch = chans.append_child("channel")
            ch.append_child_value("label", f"s{s:02d}_track_id")
            ch.append_child_value("type", "TrackId")
            ch.append_child_value("unit", "none")
            ch.append_child_value("slot", str(s))
        lay = d.append_child("layout")
        for k, v in (
            ("slots", S),
            ("joints", J),
            ("fields", ",".join(FIELDS)),
            ("order", "channel (slot*joints + joint)*4 + field, then one track_id channel per slot"),
            ("units", "metres; world frame of the calibration, z up; std_m: per-joint positional std"),
            ("missing", "NaN: joint unknown or slot empty"),
        ):
            lay.append_child_value(k, str(v))
        sk = d.append_child("skeleton")
        known = [k for k in (CANONICAL.id, "body19_hands") if tuple(joint_names) == SKELETONS[k].joint_names]
        sk.append_child_value("id", known[0] if known else "custom")
        hands = [n for n in joint_names if n in HANDS]
        if hands:  # the hand joints' names, as COCO-WholeBody names them, in MediaPipe's order per hand
            sk.append_child_value("hands", ",".join(hands))
        for jn, p in zip(joint_names, parents, strict=True):
            jj = sk.append_child("joint")
            jj.append_child_value("name", jn)
            jj.append_child_value("parent", joint_names[p] if p >= 0 else "")
        sl = d.append_child("slots")
        sl.append_child_value(
            "assignment",
            "complete: every track of the file"
            if slot_ids is not None
            else "live: a slot is given at a track's birth and freed at its death; see the track_id channels "
            f"and the {cfg.name}-events markers",
        )
        for tid, s in sorted((slot_ids or {}).items(), key=lambda x: x[1]):
            e = sl.append_child("slot")
            e.append_child_value("index", str(s))
            e.append_child_value("track_id", str(tid))
        d.append_child("clock").append_child_value(
            "timestamps", "the frame set's t_ns (host clock) mapped to LSL local_clock by a fixed offset"
        )
        self.data = pylsl.StreamOutlet(info, 1, 360)
        minfo = pylsl.StreamInfo(
            f"{cfg.name}-events", "Markers", 1, pylsl.IRREGULAR_RATE, pylsl.cf_string, sid + "-events"
        )
        minfo.desc().append_child_value("events", "birth <track id> slot <s> | death <track id> slot <s>")
        self.markers = pylsl.StreamOutlet(minfo)
        self.offset_ns = lsl_clock_offset_ns(pylsl.local_clock)
        self.sample = np.full(S * J * 4 + S, np.nan, np.float32)

    def push(
        self,
        ts: float,
        slots: dict[int, int],
        ids: np.ndarray,
        xyz: np.ndarray,
        std: np.ndarray,
        events: list[str],
    ) -> None:
        smp = self.sample
        smp[:] = np.nan
        J = self.J
        for k, tid in enumerate(ids):
            s = slots.get(int(tid), -1)
            if s < 0:
                continue
            blk = smp[s * J * 4 : (s + 1) * J * 4].reshape(J, 4)
            blk[:, :3] = xyz[k]
            blk[:, 3] = std[k]
            smp[self.S * J * 4 + s] = float(tid)
        for e in events:
            self.markers.push_sample([e], ts)
        self.data.push_sample(smp, ts)

    def close(self) -> None:
        # liblsl sends from its own threads: give connected inlets the last samples before the outlets go
        try:
            if self.data.have_consumers() or self.markers.have_consumers():
                time.sleep(CLOSE_GRACE_S)
        except Exception:  # noqa: BLE001 - closing: the outlets go either way
            pass
        del self.data, self.markers


class TrackStreamer:
    """Sends frames of tracks to the configured consumers. ``push`` never blocks on a reader; an error of
    one consumer is logged once and that consumer goes on (UDP) or is left out.

    ``slot_ids``: track id -> LSL slot when every track is known beforehand (a replay), else None."""

    def __init__(
        self,
        cfg: StreamConfig,
        fps: float,
        joint_names: Sequence[str] = CANONICAL.joint_names,
        parents: Sequence[int] = CANONICAL.parents,
        slot_ids: dict[int, int] | None = None,
    ):
        self.cfg = cfg
        self.n_joints = len(joint_names)
        names = list(joint_names)
        # OSC: the hands in messages of their own (a side whose 21 joints the skeleton has), the rest per
        # person
        self.hand_idx = {
            side: np.asarray([names.index(n) for n in H])
            for side, H in (("left", HAND_LEFT), ("right", HAND_RIGHT))
            if all(n in names for n in H)
        }
        self.person_idx = np.asarray([j for j, n in enumerate(names) if n not in HANDS], np.int64)
        self.slots = SlotMap(cfg.slots)
        if slot_ids:
            self.slots.last.update(slot_ids)
        self.lsl: _LslOutlets | None = None
        self.osc: Any = None
        self.failed: dict[str, str] = {}
        self.frames = 0
        self.push_s = 0.0
        self._warned_slots = False
        if "lsl" in cfg.kinds:
            self.lsl = _LslOutlets(cfg, fps, joint_names, parents, slot_ids)
        if "osc" in cfg.kinds:
            assert cfg.osc_to is not None
            try:
                self.osc = _osc().SimpleUDPClient(cfg.osc_to[0], cfg.osc_to[1])
            except OSError as e:
                raise StreamError(f"--osc-to {cfg.osc_to[0]}:{cfg.osc_to[1]}: {e}") from None
        self.lsl_ts: Callable[[int], float] = self._live_ts

    def _live_ts(self, t_ns: int) -> float:
        assert self.lsl is not None
        return (int(t_ns) - self.lsl.offset_ns) / 1e9

    @property
    def lsl_offset_ns(self) -> int | None:
        """host_now_ns() - LSL local_clock() in ns (the clock mapping), None without LSL."""
        return None if self.lsl is None else self.lsl.offset_ns

    def _fail(self, kind: str, e: Exception) -> None:
        if kind not in self.failed:
            log.warning("stream %s: %s (logged once; capture and the other streams go on)", kind, e)
        self.failed[kind] = f"{type(e).__name__}: {e}"

    def push(
        self, frame_index: int, t_ns: int, track_id: np.ndarray, xyz_m: np.ndarray, std_m: np.ndarray
    ) -> None:
        """One frame: track_id (K,), xyz_m (K,J,3), std_m (K,J) (the live tracker's estimate or a track
        file's row); tracks without any known joint count as absent. An empty room (K = 0) is a frame too:
        the LSL sample with every slot NaN, the OSC frame message with 0 people."""
        t0 = time.perf_counter()
        ids = np.asarray(track_id, np.int64).reshape(-1)
        J = self.n_joints if not len(ids) else -1  # an empty room: (0, J, 3); numpy cannot infer (0, -1, 3)
        xyz = np.asarray(xyz_m, np.float32).reshape(len(ids), J, 3)
        std = np.asarray(std_m, np.float32).reshape(len(ids), J)
        if xyz.shape[1] != std.shape[1]:
            raise InputError(f"xyz_m (K,J,3) and std_m (K,J) disagree: {xyz.shape} vs {std.shape}")
        keep = _present(xyz)
        ids, xyz, std = ids[keep], xyz[keep], std[keep]
        births, deaths, unslotted = self.slots.update(ids.tolist())
        if unslotted and not self._warned_slots and self.lsl is not None:
            self._warned_slots = True
            log.warning(
                "stream lsl: %d tracks present, %d slots: tracks %s are sent over OSC only (raise --slots)",
                len(ids),
                self.cfg.slots,
                unslotted,
            )
        if self.lsl is not None:
            events = [f"death {i} slot {s}" for i, s in deaths] + [f"birth {i} slot {s}" for i, s in births]
            try:
                self.lsl.push(self.lsl_ts(t_ns), self.slots.slot, ids, xyz, std, events)
            except Exception as e:  # noqa: BLE001 - a consumer's failure never stops the capture
                self._fail("lsl", e)
        if self.osc is not None:
            try:
                send = self.osc.send_message
                for i, _ in deaths:
                    send(OSC_DEATH, int(i))
                for i, _ in births:
                    send(OSC_BIRTH, int(i))
                self.osc.send(_frame_message(int(frame_index), int(t_ns), len(ids)))
                for k, tid in enumerate(ids):
                    send(OSC_PERSON, [int(tid), *xyz[k, self.person_idx].reshape(-1).tolist()])
                    for side, idx in self.hand_idx.items():
                        h = xyz[k, idx]
                        if np.isfinite(h).all(-1).any():
                            send(OSC_HAND, [int(tid), side, *h.reshape(-1).tolist()])
            except OSError as e:  # e.g. ECONNREFUSED after a listener went away: go on sending
                self._fail("osc", e)
        self.frames += 1
        self.push_s += time.perf_counter() - t0

    def close(self) -> None:
        """The outlets closed (a track alive at the end gets no death marker, as in :func:`track_events`)."""
        if self.lsl is not None:
            self.lsl.close()
            self.lsl = None

    def pylsl_now(self) -> float:
        assert self.lsl is not None
        return float(self.lsl.pylsl.local_clock())


def _present_rows(tf: TrackFile) -> np.ndarray:
    """(T,K) bool: the track has a known joint in the frame."""
    return np.isfinite(np.asarray(tf.xyz_m)).all(-1).any(-1)


def track_events(present: np.ndarray, track_id: np.ndarray) -> list[tuple[int, str, int]]:
    """Births and deaths of a track file: present (T,K) bool -> [(row t, 'birth'|'death', track id)], a
    birth at the first row of each run of presence, a death at the first row after it (no death for a
    run that lasts to the end).

    >>> track_events(np.array([[1, 0], [1, 1], [0, 1]], bool), np.array([4, 7]))
    [(0, 'birth', 4), (1, 'birth', 7), (2, 'death', 4)]
    """
    p = np.asarray(present, bool)
    prev = np.zeros(p.shape[1], bool)
    out: list[tuple[int, str, int]] = []
    for t in range(len(p)):
        for k in np.flatnonzero(prev & ~p[t]):
            out.append((t, "death", int(track_id[k])))
        for k in np.flatnonzero(p[t] & ~prev):
            out.append((t, "birth", int(track_id[k])))
        prev = p[t]
    return out


def replay(
    tf: TrackFile,
    streamer: TrackStreamer,
    speed: float = 1.0,
    loops: int = 1,
    stop: Callable[[], bool] | None = None,
    progress: Callable[[str, int, int], None] | None = None,
) -> int:
    """Send the track file ``tf`` (a :class:`roomcap.track.trackfile.TrackFile`) frame by frame at its own
    clock
    (``t_ns`` differences / ``speed``; ``speed`` 0 = as fast as possible). LSL timestamps: the first frame at
    the time the replay starts, then the file's spacing. Returns the frames sent."""
    T = tf.n_frames
    if T == 0:
        return 0
    t_file0 = int(tf.t_ns[0])
    sent = 0
    for loop in range(max(1, loops)):
        start = time.monotonic()
        if streamer.lsl is not None:
            base = streamer.pylsl_now()
            streamer.lsl_ts = lambda t_ns, b=base: b + (int(t_ns) - t_file0) / 1e9 / (speed or 1.0)
        for t in range(T):
            if stop is not None and stop():
                return sent
            if speed > 0:
                wait = (int(tf.t_ns[t]) - t_file0) / 1e9 / speed - (time.monotonic() - start)
                if wait > 0:
                    time.sleep(wait)
            streamer.push(int(tf.frame_index[t]), int(tf.t_ns[t]), tf.track_id, tf.xyz_m[t], tf.std_m[t])
            sent += 1
            if progress is not None:
                progress("stream", loop * T + t + 1, T * max(1, loops))
    return sent


def check_installed(kinds: Iterable[str]) -> None:
    """Raise :class:`StreamError` naming the extra when a stream's package is missing."""
    for k in kinds:
        if k == "lsl":
            _lsl()
        elif k == "osc":
            _osc()


def add_parser(sub: Any, resolve: Callable[[str], tuple[Any, str]]) -> None:
    """``tracks stream``: the subcommand, on the ``tracks`` parser's subparsers ``sub``; ``resolve``
    turns SESSION into (track file path, session name) (:func:`roomcap.outputs.cli.resolve_tracks`)."""
    s = sub.add_parser(
        "stream",
        help="replay a track file to LSL and/or OSC at its own clock",
        description="Replay a recorded track (SESSION's track/tracks.npz, else track/live.npz) frame by "
        "frame at its own timestamps to the Lab Streaming Layer and/or OSC, in the layout of "
        "capture-run --live "
        "--stream (see outputs/lsl_osc.py).",
    )
    s.add_argument("tracks", help="session folder or tracks.npz")
    s.add_argument(
        "--stream", action="append", required=True, metavar="KINDS", help="lsl, osc or lsl,osc (repeatable)"
    )
    s.add_argument(
        "--osc-to", default=None, metavar="HOST:PORT", help="OSC receiver (needed by --stream osc)"
    )
    s.add_argument(
        "--slots",
        type=int,
        default=None,
        help="LSL person slots (default: one per track of the file up to 64 tracks, listed in the stream's "
        "description; else as many as are present at once, given at each birth)",
    )
    s.add_argument(
        "--speed",
        type=float,
        default=1.0,
        help="1 = the recording's own pace, 2 = twice as fast, 0 = as fast as possible (default 1)",
    )
    s.add_argument("--loop", type=int, default=1, help="times to play the file (default 1)")
    s.add_argument(
        "--wait",
        type=float,
        default=0.0,
        help="seconds to wait after the outlets open, for LSL inlets to connect (default 0)",
    )
    s.add_argument("--name", default="roomcap", help="LSL stream name (default roomcap)")
    s.set_defaults(func=lambda args: _stream_cmd(args, resolve))


def _stream_cmd(args: Any, resolve: Callable[[str], tuple[Any, str]]) -> int:
    kinds = parse_kinds(args.stream)
    if args.speed < 0 or args.loop < 1 or args.wait < 0:
        raise InputError("--speed must be >= 0, --loop >= 1 and --wait >= 0.")
    check_installed(kinds)
    path, session = resolve(args.tracks)
    tf = TrackFile.load(path)
    at_once = int(_present_rows(tf).sum(1).max()) if tf.n_frames and tf.n_tracks else 0
    # default: a slot per track when they fit (the layout lists them all), else as many as are present at once
    slots = args.slots or min(256, tf.n_tracks if tf.n_tracks <= 64 else at_once) or 1
    cfg = StreamConfig(
        kinds, parse_host_port(args.osc_to) if args.osc_to else None, slots, args.name, session
    )
    slot_ids = {int(t): k for k, t in enumerate(tf.track_id)} if tf.n_tracks <= slots else None
    streamer = TrackStreamer(cfg, tf.fps, tuple(tf.joint_names), tuple(int(p) for p in tf.parents), slot_ids)
    try:
        if args.wait:
            time.sleep(args.wait)
        n = replay(tf, streamer, speed=args.speed, loops=args.loop)
    finally:
        streamer.close()
    dur = (int(tf.t_ns[-1]) - int(tf.t_ns[0])) / 1e9 if tf.n_frames else 0.0
    print(
        f"streamed {n} frames of {path} ({tf.n_tracks} tracks, {dur:.1f} s at {tf.fps:g} Hz) to "
        f"{', '.join(kinds)}"
    )
    if streamer.failed:
        print(f"  consumers that failed: {streamer.failed}")
    return 0
