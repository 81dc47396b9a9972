"""The forecast on the live view: each tracked person's next ``horizon_s`` seconds, from the live track.

``capture-run --live --view`` forecasts by default (``--no-forecast``, or ``live: {forecast: false}`` in
cams.yaml, leaves it off; the page's "forecast" toggle switches it off and on while recording). The model
is the shipped default forecaster (:func:`forecast.runtime.preview.forecast_model` ``"default"``: the GRU
checkpoint ``DEFAULT_CHECKPOINT``, else the constant-velocity baseline), fed the live track's recent frames
(:func:`roomcap.forecast.runtime.track_forecast.forecast_recent`: resampled to the model's rate, its ``n_obs``
frames at most, each person normalised at its last frame, eq. 3.8).

It never makes the live loop wait: the loop's :meth:`LiveForecast.offer` appends the step's track
estimate to a short history (a reference and a lock, no copy of images) and sets an event; a thread of
its own loads the model (torch) once and forecasts from the newest history whenever it is free, so a
forecast slower than the live loop skips the sets that came meanwhile (counted as ``superseded``). The
newest forecast is a latest-value slot (:attr:`LiveForecast.latest`) the view reads.

Its cost (:meth:`LiveForecast.summary`): the forecasting thread's CPU time per forecast and per processed
frame set, and what ``offer`` costs the live loop, reported in ``capture-run``'s live summary and on the
page.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any

import numpy as np

from roomcap.core.errors import InputError
from roomcap.forecast.runtime.preview import forecast_model
from roomcap.keypoints.skeletons import CANONICAL

log = logging.getLogger(__name__)

HORIZON_S = 1.5  # the page shows the next 1.5 s; the GRU was trained on 1 s and rolls out further
MAX_HZ = 5.0  # forecasts a second at most: a 1.5 s path needs no more, and each one redraws the page
HISTORY_S = 2.5  # kept in the history: the GRU observes 2 s (n_obs 50 at 25 Hz), plus a margin
MAX_HISTORY = 512  # frame sets in the history at most, whatever the frame rate
LH, RH = CANONICAL.joint_names.index("left_hip"), CANONICAL.joint_names.index("right_hip")


class LiveForecast:
    """The live forecast (see the module doc). ``start()`` starts its thread, ``offer(step)`` from the live
    loop, ``latest`` the newest forecast (None: none yet, or switched off), ``set_enabled(on)`` the page's
    toggle, ``stop()``."""

    def __init__(
        self,
        model: str = "default",
        horizon_s: float = HORIZON_S,
        enabled: bool = True,
        max_hz: float = MAX_HZ,
    ):
        try:
            self.kind, self.checkpoint = forecast_model(model)
        except FileNotFoundError as e:
            raise InputError(str(e)) from None
        self.horizon_s = float(horizon_s)
        self.enabled = bool(enabled)
        self.max_hz = float(max_hz)
        self.latest: dict[str, Any] | None = None
        self.model_name = self.kind if self.checkpoint is None else self.checkpoint.stem
        self._hist: deque[tuple[int, int, np.ndarray, np.ndarray]] = deque(maxlen=MAX_HISTORY)
        self._lock = threading.Lock()
        self._new = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._model: Any = None
        self._meta: dict[str, Any] = {"fps": 25.0}
        self.ready = threading.Event()  # the model is loaded
        self.n_offered = 0  # processed frame sets handed over
        self.n_forecast = 0  # forecasts computed
        self.n_superseded = 0  # sets with people that a newer one replaced before the thread was free
        self.cpu_s = 0.0  # the forecasting thread's CPU time, forecasts only (not the model's loading)
        self.load_s = 0.0
        self.loop_s = 0.0  # what offer() cost the live loop's thread
        self.last_ms = 0.0  # the newest forecast's CPU time
        self.error: str | None = None
        self._pending = False
        # called on the forecasting thread after each new forecast (the view sends it at once: under load
        # the next frame set can come after the forecast's whole horizon, which would never be drawn)
        self.listeners: list[Callable[[], None]] = []

    # ------------------------------------------------------------------ live loop
    def offer(self, step: Any) -> None:
        """Called by the live loop after the stages: the step's track estimate into the history."""
        t0 = time.thread_time()
        self.n_offered += 1
        est = step.outputs.get("tracks")
        if est is not None:
            ids = np.asarray(est.track_id, np.int64).reshape(-1)
            xyz = np.asarray(est.xyz_m, np.float32).reshape(len(ids), CANONICAL.n_joints, 3)
            with self._lock:
                self._hist.append((int(step.frameset.t_ns), int(step.frameset.index), ids, xyz))
                t_old = int(step.frameset.t_ns) - int(HISTORY_S * 1e9)
                while self._hist and self._hist[0][0] < t_old:
                    self._hist.popleft()
                if self._pending:
                    self.n_superseded += 1
                self._pending = bool(len(ids)) and self.enabled
            if self._pending:
                self._new.set()
            elif not len(ids):
                self.latest = None  # nobody in view: no forecast to draw
        self.loop_s += time.thread_time() - t0

    def set_enabled(self, on: bool) -> None:
        """The page's toggle: off stops forecasting (no CPU spent) and clears the drawn forecast."""
        self.enabled = bool(on)
        if not self.enabled:
            self.latest = None
        else:
            self._new.set()

    # ------------------------------------------------------------------ its thread
    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="live-forecast", daemon=True)
        self._thread.start()

    def stop(self, timeout_s: float = 5.0) -> None:
        self._stop.set()
        self._new.set()
        if self._thread is not None:
            self._thread.join(timeout_s)

    def load(self) -> None:
        """Load the model (torch, once; off the live loop's thread) and run it once on a still pose (the
        first call allocates)."""
        if self.ready.is_set():
            return
        t0 = time.perf_counter()
        if self.checkpoint is not None:
            import torch  # lazy: loads torch

            from roomcap.forecast.runtime.checkpoint import load_checkpoint

            # one thread: the 2D stage's groups hold the cores; the GRU on 3 people takes ~5 ms on one
            torch.set_num_threads(1)
            self._model, self._meta = load_checkpoint(self.checkpoint, skeleton=CANONICAL.id)
        still = np.zeros((2, 1, CANONICAL.n_joints, 3), np.float32)
        still[..., 0] = np.linspace(-0.2, 0.2, CANONICAL.n_joints)
        still[..., 2] = 1.0
        self.forecast(np.array([0.0, 0.04]), still)
        self.load_s = time.perf_counter() - t0
        self.ready.set()

    def forecast(self, t_s: np.ndarray, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(H,K,J,3), t (H,), present (K,) from the frames ``xyz (T,K,J,3)`` at ``t_s (T,)``."""
        from roomcap.forecast.runtime.track_forecast import forecast_recent  # lazy: loads torch

        return forecast_recent(self._model, self._meta, t_s, xyz, self.horizon_s)

    def _run(self) -> None:
        try:
            self.load()
        except Exception as e:  # noqa: BLE001 - the page goes on without a forecast; said once
            self.error = f"{type(e).__name__}: {e}"
            log.warning("live forecast: cannot load %s (%s); no forecast on the page", self.model_name, e)
            return
        while not self._stop.is_set():
            if not self._new.wait(0.25):
                continue
            self._new.clear()
            t0 = time.monotonic()
            if not self._stop.is_set() and self.step_once():  # then a pause: max_hz forecasts a second
                self._stop.wait(max(0.0, t0 + 1.0 / self.max_hz - time.monotonic()))

    def step_once(self) -> bool:
        """Forecast from the newest history if a frame set with people came since the last forecast (and
        the forecast is on); the newest forecast into :attr:`latest`. True when one was computed."""
        with self._lock:
            hist = list(self._hist) if self._pending and self.enabled else []
            self._pending = False
        if not hist:
            return False
        t0 = time.thread_time()
        try:
            fc = self.build(hist)
        except Exception as e:  # noqa: BLE001 - a bad forecast never stops the view; logged once
            if self.error is None:
                log.exception("live forecast failed")
            self.error = f"{type(e).__name__}: {e}"
            return False
        dt = time.thread_time() - t0
        self.cpu_s += dt
        self.last_ms = 1e3 * dt
        self.n_forecast += 1
        if self.enabled:
            self.latest = fc
            for f in self.listeners:
                f()
        return True

    def build(self, hist: list[tuple[int, int, np.ndarray, np.ndarray]]) -> dict[str, Any]:
        """The forecast of the tracks present in the newest frame set of ``hist`` ((t_ns, frame, ids, xyz
        (K,J,3)) oldest first): ``{"frame", "t_ns", "model", "t_s" (H,), "ids" (K,), "xyz" (K,H,J,3)}``."""
        t_last, frame, ids, _ = hist[-1]
        ids = [int(i) for i in ids]
        col = {tid: k for k, tid in enumerate(ids)}
        J = CANONICAL.n_joints
        xyz = np.full((len(hist), len(ids), J, 3), np.nan, np.float32)
        for t, (_, _, hid, hx) in enumerate(hist):
            for k, tid in enumerate(hid):
                c = col.get(int(tid))
                if c is not None:
                    xyz[t, c] = hx[k]
        t_s = (np.asarray([h[0] for h in hist], np.int64) - t_last) / 1e9
        out, t_out, present = self.forecast(t_s, xyz)
        keep = np.flatnonzero(present)
        return {
            "frame": frame,
            "t_ns": t_last,
            "model": self.model_name,
            "t_s": np.asarray(t_out, np.float64),
            "ids": [ids[k] for k in keep],
            "xyz": np.moveaxis(np.asarray(out, np.float32), 1, 0)[keep],
        }

    # ------------------------------------------------------------------ cost
    def summary(self) -> dict[str, Any]:
        n = max(1, self.n_offered)
        return {
            "model": self.model_name,
            "on": self.enabled,
            "offered": self.n_offered,
            "forecasts": self.n_forecast,
            "superseded": self.n_superseded,
            "ms_per_forecast": 1e3 * self.cpu_s / max(1, self.n_forecast),
            "ms_per_set": 1e3 * self.cpu_s / n,
            "loop_ms_per_set": 1e3 * self.loop_s / n,
            "load_s": self.load_s,
            "error": self.error,
        }

    def summary_line(self) -> str:
        s = self.summary()
        line = (
            f"forecast ({s['model']}, {self.horizon_s:g} s{'' if s['on'] else ', switched off'}): "
            f"{s['forecasts']} forecasts for {s['offered']} frame sets ({s['superseded']} superseded), "
            f"{s['ms_per_forecast']:.1f} ms CPU each, {s['ms_per_set']:.2f} ms per frame set on its thread, "
            f"{s['loop_ms_per_set']:.3f} ms in the live loop"
        )
        return line + (f"; failed: {s['error']}" if s["error"] else "")

    def view_data(self, now_ns: int | None = None) -> dict[str, Any]:
        """What the page draws: per person the path of the hips' midpoint (H,3) and the ghost pose at the
        horizon (J,3), with the cost. ``now_ns``: the drawn frame set's time; a forecast that started more
        than its horizon before it is not drawn (its whole path is in the past)."""
        s = self.summary()
        out: dict[str, Any] = {
            "on": self.enabled,
            "model": s["model"],
            "ms": round(self.last_ms, 2),
            "ms_per_set": round(s["ms_per_set"], 2),
            "horizon_s": self.horizon_s,
            "tracks": [],
        }
        fc = self.latest
        if not self.enabled or fc is None:
            return out
        if now_ns is not None and now_ns - fc["t_ns"] > self.horizon_s * 1e9:
            return out
        out["frame"] = fc["frame"]
        for tid, x in zip(fc["ids"], fc["xyz"], strict=True):
            path = 0.5 * (x[:, LH] + x[:, RH])  # (H,3)
            out["tracks"].append({"id": int(tid), "path": path, "ghost": x[-1]})
        return out
