"""The Pose2Sim multi-person demo as live cameras, for the live benches: its calibration and its 4 videos as
looping, real-time file cameras in a ``cams.yaml``."""

from __future__ import annotations

from pathlib import Path

from roomcap.calibrate.formats import import_rig

CAMS = ("cam01", "cam02", "cam03", "cam04")


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
