"""The Pose2Sim multi-person demo as live cameras, for the live benches: its calibration and its 4 videos as
looping, real-time file cameras in a ``cams.yaml``."""

from __future__ import annotations

import os
import re
import threading
import time
from pathlib import Path

from roomcap.calibrate.formats import import_rig

CAMS = ("cam01", "cam02", "cam03", "cam04")
# --shared's default: $ROOMCAP_SHARED, else the shared folder beside the checkout
SHARED = os.environ.get("ROOMCAP_SHARED", str(Path(__file__).resolve().parents[2] / "shared"))
DEMO = Path("data/pose2sim/demo-wheel-0.10.49/Demo_MultiPerson")  # the multi-person demo, under --shared
# where a live process's CPU goes: thread-name patterns of the recorder and the 2D camera groups
THREAD_GROUPS = (
    ("decode (grab-*)", r"^grab-"),
    ("encode (write-*)", r"^write-"),
    ("2D workers", r"^live-keypoints"),
)


class _Sampler:
    """Samples CPU seconds every ``every`` s on a thread of its own while in use (``with``)."""

    def __init__(self, every: float) -> None:
        self._every = every
        self._stop = threading.Event()
        self._t = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self._stop.wait(self._every):
            self.sample()

    def sample(self) -> None:
        raise NotImplementedError

    def __enter__(self):
        self.sample()
        self._t.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._t.join(2)


class ThreadCpu(_Sampler):
    """CPU seconds per thread name of this process, sampled every ``every`` s (a thread's last value stays
    when it ends; its CPU before it was first seen, its start-up, is left out)."""

    def __init__(self, every: float = 0.2) -> None:
        super().__init__(every)
        self.cpu: dict[str, float] = {}
        self.first: dict[str, float] = {}

    def sample(self) -> None:
        for t in threading.enumerate():
            if t.ident is None or not t.is_alive():
                continue
            try:
                v = time.clock_gettime(time.pthread_getcpuclockid(t.ident))
            except (OSError, ProcessLookupError):
                continue
            self.first.setdefault(t.name, v)
            self.cpu[t.name] = v

    def used(self, name: str) -> float:
        """CPU seconds of the thread since it was first seen (0.0 if never)."""
        return self.cpu.get(name, 0.0) - self.first.get(name, 0.0)

    def groups(self, groups=THREAD_GROUPS, other: str = "other threads") -> dict[str, float]:
        """CPU seconds by ``groups`` ((label, thread-name pattern), ...), the live loop (threads ``live``,
        ``live-3d``) and the rest."""
        rows = {g: 0.0 for g, _ in groups} | {"live loop (live, live-3d)": 0.0, other: 0.0}
        for name in self.cpu:
            g = next((g for g, pat in groups if re.match(pat, name)), None)
            if g is None:
                g = "live loop (live, live-3d)" if name in ("live", "live-3d") else other
            rows[g] += self.used(name)
        return rows


class TreeCpu(_Sampler):
    """CPU seconds of processes and their children (a headless Chromium's renderer, GPU and utility
    processes), by process type; ``pids`` may get its pid after the start."""

    def __init__(self, pids: list, every: float = 0.5) -> None:
        super().__init__(every)
        self.pids = pids
        self.kind: dict = {}  # pid -> Chromium's process type (renderer, gpu-process, utility, browser)
        self._cpu: dict = {}
        self._first: dict = {}

    def sample(self) -> None:
        import psutil

        for pid in self.pids:
            try:
                root = psutil.Process(pid)
                procs = [root, *root.children(recursive=True)]
            except psutil.Error:
                continue
            for p in procs:
                try:
                    t = p.cpu_times()
                    if p.pid not in self.kind:
                        types = [a[7:] for a in p.cmdline() if a.startswith("--type=")]
                        self.kind[p.pid] = types[0] if types else "browser"
                except psutil.Error:
                    continue
                self._first.setdefault(p.pid, t.user + t.system)
                self._cpu[p.pid] = t.user + t.system

    def used(self) -> float:
        return sum(v - self._first[k] for k, v in self._cpu.items())

    def by_kind(self) -> dict:
        out: dict = {}
        for k, v in self._cpu.items():
            out[self.kind[k]] = out.get(self.kind[k], 0.0) + v - self._first[k]
        return out


def write_looping_cams(demo: Path, folder: Path) -> Path:
    """``folder/rig.toml`` from the demo's Qualisys calibration and ``folder/cams.yaml`` naming its videos as
    looping file cameras replayed at their own rate; returns the cams.yaml."""
    import_rig(demo / "calibration" / "Calib.qca.txt").save(folder / "rig.toml")
    cams = folder / "cams.yaml"
    cams.write_text(
        "calibration: rig.toml\ncameras:\n"
        + "".join(
            f"  - {{name: {c}, source: '{demo / 'videos' / (c + '.mp4')}', loop: true, realtime: true}}\n"
            for c in CAMS
        )
    )
    return cams


def loopback_lsl(folder: Path) -> Path:
    """Keep LSL on this machine: ``folder/lsl_api.cfg`` (``ResolveScope = machine``, IPv4 loopback as the
    only known peer), named in ``LSLAPICFG`` / ``LSL_API_CFG`` for this process and the ones it starts.
    liblsl reads the file when it is first loaded: call this before ``import pylsl``."""
    import os

    cfg = folder / "lsl_api.cfg"
    cfg.write_text(
        "[ports]\nIPv6 = disable\n[multicast]\nResolveScope = machine\n[lab]\nKnownPeers = {127.0.0.1}\n"
    )
    os.environ["LSLAPICFG"] = os.environ["LSL_API_CFG"] = str(cfg)
    return cfg


class LslReader:
    """An LSL inlet on the stream with ``source_id`` (``roomcap-<session>``) pulling every sample in a thread
    of its own: ``rows`` (the samples), ``ts`` (their LSL timestamps), ``connected_at`` (``time.monotonic()``
    when the inlet was open; None until then or when no stream was found in ``resolve_s``)."""

    def __init__(self, source_id: str, resolve_s: float = 10.0):
        import threading

        self.source_id, self.resolve_s = source_id, resolve_s
        self.rows: list = []
        self.ts: list = []
        self.connected_at: float | None = None
        self._open = threading.Event()
        self._stop = threading.Event()
        self._t = threading.Thread(target=self._run, name="lsl-reader", daemon=True)

    def start(self) -> LslReader:
        self._t.start()
        return self

    def wait_open(self, timeout_s: float | None = None) -> bool:
        """Wait until the inlet is open (or the stream was not found); whether it is open."""
        self._open.wait(timeout_s)
        return self.connected_at is not None

    def _run(self) -> None:
        import time

        import pylsl

        try:
            found = pylsl.resolve_byprop("source_id", self.source_id, 1, self.resolve_s)
            if not found:
                return
            inlet = pylsl.StreamInlet(found[0])
            inlet.open_stream(10.0)
            self.connected_at = time.monotonic()
        finally:
            self._open.set()
        while not self._stop.is_set():
            d, ts = inlet.pull_chunk(timeout=0.2)
            self.rows.extend(d)
            self.ts.extend(ts)

    @property
    def n(self) -> int:
        return len(self.rows)

    def stop(self, drain_s: float = 0.5) -> None:
        """Stop pulling (after ``drain_s`` more seconds of it: samples still on their way)."""
        import time

        time.sleep(drain_s)
        self._stop.set()
        self._t.join(2.0)


def match_lsl_to_frames(lsl_ts, frame_t_ns, tol_ms: float = 2.0):
    """Each LSL sample's frame in a track file: its timestamp (LSL's ``local_clock`` seconds) mapped back to
    the host clock of ``capture.sources.host_now_ns`` (both CLOCK_MONOTONIC based; the offset measured here
    equals the recording process's to a few µs) and matched to the nearest ``frame_t_ns``, each frame to
    the first sample only (a set the track stage skipped as late can carry the time of the set before it).
    Returns ``(frame row per sample, -1 where none is left within tol_ms; the error in ms per sample)``."""
    import numpy as np
    import pylsl

    from roomcap.outputs.lsl_osc import lsl_clock_offset_ns

    t_ns = np.asarray(lsl_ts, np.float64) * 1e9 + lsl_clock_offset_ns(pylsl.local_clock)
    f = np.asarray(frame_t_ns, np.float64)
    if not len(t_ns) or not len(f):
        return np.full(len(t_ns), -1), np.full(len(t_ns), np.inf)
    d = np.abs(t_ns[:, None] - f[None, :])
    row, err = d.argmin(1), d.min(1) / 1e6
    row = np.where(err <= tol_ms, row, -1)
    seen: set[int] = set()
    for i, r in enumerate(row.tolist()):
        if r in seen:
            row[i] = -1
        seen.add(r)
    return row, err
