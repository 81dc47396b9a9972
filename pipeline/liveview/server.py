"""The live view of ``capture-run --live --view``: a local page that shows the recording as it happens.

The page (``live.html`` + ``live.js``, the report's 3D drawing in ``viewer3d.js``) shows every camera's
latest frame with its 2D detections and the 3D tracks reprojected into it, the room in 3D with each
track in its colour, who is present, per-camera fps and dropped frames, and the end-to-end latency
(frame capture -> page drawn).

Threads and what never waits:

- the live loop calls :meth:`LiveView.offer` with each processed step: one assignment and an event,
  nothing else (no copy, no encoding, no I/O);
- a producer thread takes the newest step, builds the state message (tracks, 2D detections,
  reprojections, counters; at most ``state_hz`` a second) and, only while a page is connected, one
  reduced JPEG per camera at most ``image_hz`` a second per camera;
- an asyncio loop (aiohttp) in its own thread serves the page and one WebSocket per page. Each page
  has a latest-value slot per message kind: a newer message replaces one not yet sent (counted as a
  dropped update), so a slow or closed page loses view updates, never frames, and never slows the
  producer or the live loop.

Messages (server -> page): ``hello`` (text, JSON: cameras, rig, skeleton) on connect; ``state`` (text,
JSON) per update; a camera image (binary: 2-byte big-endian header length, the header as JSON
``{"cam", "seq", "t_capture_ms", "w", "h", "src_wh"}``, then the JPEG). The page answers each drawn
state with ``{"ack": seq, "t_capture_ms": ...}``: the server's own latency measure
(:meth:`LiveView.latency_ms`, from outside the page). The state's ``forecast`` (with a forecaster,
:mod:`roomcap.pipeline.live_forecast`): each tracked person's next seconds as ``{"id", "path" (H,3) the
hips' midpoint, "ghost" (J,3) the pose at the horizon}`` and its cost; the page's toggle sends
``{"forecast": false|true}``, which switches the forecaster off or on. A forecast that comes after its
step's state was sent sends that state again with it (``"refresh": true``, no image; the page acknowledges
it only when it is the first drawing of that frame set): under load the next step can come after the
forecast's whole horizon.

Hands: ``hello`` names the 44 hand points (``hand_names``: the two wrists, then the 42 hand joints) and
their tree (``hand_parents``). A track estimate with hands (its ``joint_names`` has them) gives its track
``"hands"`` (44×3) beside the body's ``xyz`` (body19, by name), and ``hproj`` the hands reprojected per
camera; 2D detections in a ``*_hands`` layout give ``hdet`` per camera. Without hands the state is as
before.

Access: the server listens on 127.0.0.1 by default. Another address (``--view-host``) needs a token
(``--view-token TOKEN``, or ``auto`` for a random one printed once in the page's URL); every request
without it is answered 403. Timestamps: ``t_capture_ms`` is the newest frame of the set's host arrival
time (``capture.sources.host_now_ns``, UNIX time in ms), the page's clock is ``Date.now()`` on the same
machine.
"""

from __future__ import annotations

import asyncio
import errno
import json
import logging
import re
import secrets
import socket
import threading
import time
from collections import deque
from dataclasses import dataclass
from importlib import resources
from typing import Any

import cv2
import numpy as np

from roomcap.calibrate.camera import CameraRig
from roomcap.capture.config import CaptureConfig
from roomcap.capture.live import LiveRunner, LiveStep, jump_line
from roomcap.capture.sources import host_now_ns, jpeg_size
from roomcap.core.errors import InputError
from roomcap.keypoints.skeletons import CANONICAL, HANDS, convert, get_skeleton
from roomcap.pipeline.report import rig_cameras_data
from roomcap.pipeline.report.views import HAND2D, HAND2D_PARENTS

log = logging.getLogger(__name__)

DEFAULT_PORT = 8765
LOOPBACK = ("127.0.0.1", "localhost", "::1")
REFRESH_WAIT_S = 0.15  # a new forecast of a set already sent waits this long for the next set to carry it


@dataclass(frozen=True)
class ViewConfig:
    """host/port: where the page is served; token: needed in every request when not on loopback
    (``auto``: a random one); image_hz: camera images per second and camera at most; image_width_px:
    the images' width on the page (reduced, aspect kept); jpeg_quality 1..100; state_hz: track/counter
    updates per second at most."""

    host: str = "127.0.0.1"
    port: int = DEFAULT_PORT
    token: str | None = None
    image_hz: float = 5.0
    image_width_px: int = 360
    jpeg_quality: int = 70
    state_hz: float = 15.0

    def __post_init__(self) -> None:
        if self.host not in LOOPBACK and not self.token:
            raise InputError(
                f"--view-host {self.host} serves the live view to other machines: pass --view-token auto "
                "(a random token, printed once in the page's URL) or --view-token TOKEN; without one, "
                "keep the default --view-host 127.0.0.1."
            )
        if not 0 <= int(self.port) < 65536:
            raise InputError(f"--view-port must be 0..65535, got {self.port}.")


def _asset(name: str) -> str:
    return resources.files(__package__).joinpath(name).read_text(encoding="utf-8")


def _report_asset(name: str) -> str:
    return resources.files("roomcap.pipeline.report_assets").joinpath(name).read_text(encoding="utf-8")


def page_html() -> str:
    """The page, with its script and the report's 3D viewer inlined (no other request, no network)."""
    return (
        _asset("live.html")
        .replace("__VIEWER3D__", _report_asset("viewer3d.js"))
        .replace("__SCRIPT__", _asset("live.js"))
        .replace("__STYLE__", _asset("live.css"))
    )


def _free_port(host: str) -> int:
    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def bind_socket(host: str, port: int) -> socket.socket:
    """A listening TCP socket on host:port, or an :class:`InputError` naming the port and a free one."""
    fam = socket.AF_INET6 if ":" in host else socket.AF_INET
    s = socket.socket(fam, socket.SOCK_STREAM)
    try:
        s.bind((host, port))
        s.listen(16)
    except OSError as e:
        s.close()
        if e.errno == errno.EADDRINUSE:
            raise InputError(
                f"--view-port {port} is in use on {host} (another program, or another capture-run --view). "
                f"Pass --view-port {_free_port(host)} (free now) or --view-port 0 (any free port)."
            ) from None
        if e.errno in (errno.EADDRNOTAVAIL, errno.EAFNOSUPPORT) or isinstance(e, socket.gaierror):
            raise InputError(f"--view-host {host}: not an address of this machine ({e.strerror}).") from None
        raise InputError(f"--view-host {host} --view-port {port}: cannot listen ({e}).") from None
    s.setblocking(False)
    return s


def _flat(a: np.ndarray, nd: int = 1) -> list[float]:
    """Flattened and rounded; NaN stays NaN here and is written as null by :func:`to_json`."""
    return np.round(np.asarray(a, np.float64).reshape(-1), nd).tolist()  # type: ignore[no-any-return]


_NAN = re.compile(r"(?<=[\[,:\s])(?:NaN|-?Infinity)(?=[\],}\s])")


def _by_name(a: np.ndarray, names, wanted) -> np.ndarray:
    """``a (..., J, D)`` in the layout ``names`` -> ``(..., len(wanted), D)``, NaN for a name it lacks."""
    idx = [names.index(n) if n in names else -1 for n in wanted]
    out = np.asarray(a, np.float64)[..., [max(i, 0) for i in idx], :]
    out[..., [k for k, i in enumerate(idx) if i < 0], :] = np.nan
    return out


def to_json(obj: Any) -> str:
    """JSON for the page: non-finite numbers as null (JavaScript's JSON.parse takes no NaN); a name in
    quotes is never touched.

    >>> to_json({"a": [1.5, float("nan")], "NaN": "x"})
    '{"a": [1.5, null], "NaN": "x"}'
    """
    return _NAN.sub("null", json.dumps(obj))


class _Client:
    def __init__(self) -> None:
        self.pending: dict[str, Any] = {}
        self.ready = asyncio.Event()
        self.dropped = 0


class LiveView:
    """The live view's server. ``start()`` binds (a port in use raises :class:`InputError`) and serves;
    ``offer(step)`` from the live loop; ``stop()`` ends it within a second or two."""

    def __init__(
        self,
        cfg: ViewConfig,
        capture: CaptureConfig,
        runner: LiveRunner | None,
        recorder: Any = None,
        rig: CameraRig | None = None,
        forecast: Any = None,
    ):
        if cfg.token == "auto":
            cfg = ViewConfig(**{**cfg.__dict__, "token": secrets.token_urlsafe(16)})
        self.cfg = cfg
        self.capture = capture
        self.runner = runner
        self.recorder = recorder
        self.cameras = tuple(capture.names)
        self.rig = rig
        self.forecast = forecast  # a pipeline.live_forecast.LiveForecast, or None (no forecast on the page)
        self._refresh = False  # a new forecast of the step last sent: send its state again
        self._sent: LiveStep | None = None  # the step whose state was last sent
        if forecast is not None:
            forecast.listeners.append(self._forecast_ready)
        self._latest: LiveStep | None = None
        self._new = threading.Event()
        self._stop = threading.Event()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._clients: set[_Client] = set()
        self._threads: list[threading.Thread] = []
        self._sock: socket.socket | None = None
        self.port = cfg.port
        self.seq = 0
        self.states_sent = 0
        self.images_sent = 0
        self.encode_s = 0.0  # producer CPU time (thread time)
        self._acks: deque[float] = deque(maxlen=5000)
        self._split: deque[tuple[float, float]] = deque(maxlen=5000)
        self._last_img: dict[str, float] = {}
        self._last_state = 0.0
        self._fps: dict[str, tuple[float, int, float | None]] = {}
        self.clients_seen = 0
        self._dropped_gone = 0  # updates dropped for pages that have gone
        self._rig_data: dict[str, Any] | None = None
        self.client_errors = 0

    # ------------------------------------------------------------------ public
    @property
    def url(self) -> str:
        host = "127.0.0.1" if self.cfg.host in ("0.0.0.0", "::") else self.cfg.host
        host = f"[{host}]" if ":" in host else host
        q = f"/?token={self.cfg.token}" if self.cfg.token else "/"
        return f"http://{host}:{self.port}{q}"

    def start(self) -> None:
        try:
            import aiohttp  # noqa: F401  # lazy: the view extra; checked before binding
        except ImportError:
            raise InputError(
                "--view needs the aiohttp package, which is not installed: pip install 'roomcap[view]'."
            ) from None
        self._sock = bind_socket(self.cfg.host, self.cfg.port)
        self.port = int(self._sock.getsockname()[1])
        started = threading.Event()
        err: list[BaseException] = []
        t = threading.Thread(target=self._serve, args=(started, err), name="liveview-server", daemon=True)
        t.start()
        if not started.wait(10.0) or err:
            raise InputError(f"live view: the server did not start ({err[0] if err else 'timeout'}).")
        p = threading.Thread(target=self._produce, name="liveview-producer", daemon=True)
        p.start()
        self._threads = [t, p]

    def _forecast_ready(self) -> None:
        """The forecaster's thread: a new forecast (of the newest step with people, usually the one last
        sent); the producer sends the state again with it instead of waiting for the next step."""
        self._refresh = True
        self._new.set()

    def offer(self, step: LiveStep) -> None:
        """Called by the live loop: keep the newest step (the previous one, if not yet taken, is dropped)."""
        self._latest = step
        self._new.set()

    def latency_ms(self) -> list[float]:
        """Frame capture -> the page drew it, ms, one per acknowledged state (measured at the server)."""
        return list(self._acks)

    def latency_split_ms(self) -> list[tuple[float, float]]:
        """Per acknowledged state: (frame capture -> the state built here, built -> the page drew it), ms."""
        return list(self._split)

    @property
    def n_clients(self) -> int:
        return len(self._clients)

    @property
    def dropped_updates(self) -> int:
        return sum(c.dropped for c in list(self._clients)) + self._dropped_gone

    def stop(self) -> None:
        self._stop.set()
        self._new.set()
        loop = self._loop
        if loop is not None and loop.is_running():
            fut = asyncio.run_coroutine_threadsafe(self._shutdown(), loop)
            try:
                fut.result(2.0)
            except Exception:  # noqa: BLE001 - stopping: nothing to keep
                log.debug("live view: shutdown", exc_info=True)
        for t in self._threads:
            t.join(2.0)

    # ------------------------------------------------------------------ server thread
    def _serve(self, started: threading.Event, err: list[BaseException]) -> None:
        from aiohttp import web  # lazy: loads aiohttp (the view extra)

        loop = asyncio.new_event_loop()
        self._loop = loop
        asyncio.set_event_loop(loop)
        app = web.Application()
        app.router.add_get("/", self._page)
        app.router.add_get("/ws", self._ws)
        app.router.add_get("/status.json", self._status)
        self._app_runner = web.AppRunner(app, handle_signals=False, access_log=None)
        try:
            loop.run_until_complete(self._app_runner.setup())
            loop.run_until_complete(web.SockSite(self._app_runner, self._sock).start())
        except BaseException as e:  # noqa: BLE001 - reported to start()
            err.append(e)
            started.set()
            return
        started.set()
        try:
            loop.run_forever()
        finally:
            loop.close()

    async def _shutdown(self) -> None:
        for c in list(self._clients):
            c.pending["close"] = True
            c.ready.set()
        await self._app_runner.cleanup()
        asyncio.get_running_loop().call_soon(asyncio.get_running_loop().stop)

    def _allowed(self, request: Any) -> bool:
        return not self.cfg.token or secrets.compare_digest(request.query.get("token", ""), self.cfg.token)

    async def _page(self, request: Any) -> Any:
        from aiohttp import web  # lazy: loads aiohttp

        if not self._allowed(request):
            return web.Response(status=403, text="roomcap live view: add ?token=... (printed by capture-run)")
        return web.Response(text=page_html(), content_type="text/html", headers={"Cache-Control": "no-store"})

    async def _status(self, request: Any) -> Any:
        from aiohttp import web  # lazy: loads aiohttp

        if not self._allowed(request):
            return web.Response(status=403)
        return web.json_response(self.status())

    async def _ws(self, request: Any) -> Any:
        from aiohttp import WSMsgType, web  # lazy: loads aiohttp

        if not self._allowed(request):
            return web.Response(status=403)
        # no permessage-deflate: JPEGs do not compress, and zlib on every update costs the server its CPU
        ws = web.WebSocketResponse(heartbeat=10.0, max_msg_size=1 << 16, compress=False)
        try:
            await ws.prepare(request)
        except ConnectionError as e:  # the page went away before the handshake was written
            self._page_gone(e)
            return web.Response(status=410)  # written to nobody: aiohttp drops the reset connection quietly
        client = _Client()
        client.pending["hello"] = json.dumps(self.hello())
        client.ready.set()
        self._clients.add(client)
        self.clients_seen += 1
        sender = asyncio.get_running_loop().create_task(self._send(ws, client))
        try:
            async for msg in ws:
                if msg.type == WSMsgType.TEXT:
                    self._on_page_message(msg.data)
                elif msg.type in (WSMsgType.ERROR, WSMsgType.CLOSE):
                    break
        finally:
            self._clients.discard(client)
            self._dropped_gone += client.dropped
            sender.cancel()
        return ws

    async def _send(self, ws: Any, client: _Client) -> None:
        try:
            while not ws.closed:
                await client.ready.wait()
                client.ready.clear()
                items, client.pending = client.pending, {}
                if items.pop("close", False):
                    await ws.close()
                    return
                for _, m in sorted(items.items(), key=lambda kv: kv[0] != "hello"):
                    if isinstance(m, bytes):
                        await ws.send_bytes(m)
                    else:
                        await ws.send_str(m)
        except (ConnectionError, RuntimeError) as e:  # the page went away: log once per page, go on
            self._page_gone(e)

    def _page_gone(self, e: BaseException) -> None:
        """A page closed its connection while we wrote to it: one line, no traceback."""
        self.client_errors += 1
        log.info("live view: a page disconnected (%s: %s)", type(e).__name__, e)

    def _on_page_message(self, text: str) -> None:
        try:
            m = json.loads(text)
        except ValueError:
            return
        if isinstance(m, dict) and isinstance(m.get("forecast"), bool) and self.forecast is not None:
            self.forecast.set_enabled(m["forecast"])  # the page's toggle
            log.info("live view: forecast switched %s from the page", "on" if m["forecast"] else "off")
            return
        try:
            t = float(m["t_capture_ms"])
        except (ValueError, KeyError, TypeError):
            return
        if "ack" in m:
            now = host_now_ns() / 1e6
            self._acks.append(now - t)
            sent = m.get("t_sent_ms")
            if isinstance(sent, (int, float)):
                self._split.append((float(sent) - t, now - float(sent)))

    def _publish(self, msgs: dict[str, Any]) -> None:  # on the loop
        for c in self._clients:
            for k, m in msgs.items():
                if k in c.pending:
                    c.dropped += 1
                c.pending[k] = m
            c.ready.set()

    # ------------------------------------------------------------------ producer thread
    def _produce(self) -> None:
        while not self._stop.is_set():
            if not self._new.wait(0.25):
                continue
            self._new.clear()
            step = self._latest
            refresh, self._refresh = self._refresh, False
            if step is None or self._stop.is_set() or not self._clients:
                continue
            if step is self._sent and not refresh:
                continue
            if step is self._sent:  # a new forecast of the set already sent: a set that comes within
                # REFRESH_WAIT_S carries it (the page draws once, not twice); else this state goes again
                self._new.wait(REFRESH_WAIT_S)
                if self._latest is not step:
                    continue
            t0 = time.thread_time()
            try:
                # a new step: its state and images; the same step again: a new forecast of it, the state only
                msgs = self.messages(step, refresh=step is self._sent)
                if "state" in msgs:
                    self._sent = step
            except Exception:  # noqa: BLE001 - a bad frame never stops the view
                log.exception("live view: could not build an update")
                msgs = {}
            self.encode_s += time.thread_time() - t0
            if msgs and self._loop is not None and not self._stop.is_set():
                try:
                    self._loop.call_soon_threadsafe(self._publish, msgs)
                except RuntimeError:  # stop() closed the loop after the check above: nothing left to serve
                    return

    def messages(self, step: LiveStep, now: float | None = None, refresh: bool = False) -> dict[str, Any]:
        """The messages for this step: ``state`` (rate-limited) and ``img:<cam>`` (rate-limited).
        ``refresh``: the step's state was sent and its forecast came since: the state again, no image (not
        rate-limited; marked ``"refresh": true``: the page acknowledges only a set's first drawing)."""
        now = time.monotonic() if now is None else now
        out: dict[str, Any] = {}
        fs = step.frameset
        frames = [f for f in fs.frames.values() if f is not None]
        t_cap_ms = max(f.t_host_ns for f in frames) / 1e6 if frames else host_now_ns() / 1e6
        if refresh:
            self.seq += 1
            out["state"] = to_json({**self.state(step, t_cap_ms), "refresh": True})
            self.states_sent += 1
            return out
        if now - self._last_state >= 1.0 / self.cfg.state_hz:
            self._last_state = now
            self.seq += 1
            out["state"] = to_json(self.state(step, t_cap_ms))
            self.states_sent += 1
        else:  # an image goes with the state of its own frame set (the page draws its detections on it)
            return out
        for cam in self.cameras:
            f = fs.frames.get(cam)
            if f is None or not f.has_image or now - self._last_img.get(cam, -1e9) < 1.0 / self.cfg.image_hz:
                continue
            self._last_img[cam] = now
            if f.image is not None:
                img = np.asarray(f.image)
                h, w = img.shape[:2]
            else:  # a camera's JPEG: decoded at the smallest of 1/2, 1/4, 1/8 still as wide as the page's
                w, h = jpeg_size(f.jpeg)
                r = 8
                while r > 1 and w / r < min(self.cfg.image_width_px, w):
                    r //= 2
                # the 2D stage's decoding of the same JPEG where it is large enough (it decodes at 1/k)
                k, shown = step.outputs.get("decoded", {}).get(cam, (None, None))
                img = shown if shown is not None and k <= r else f.decoded(r)
            W = min(self.cfg.image_width_px, w)
            H = max(1, round(h * W / w))
            # bilinear: a preview, 10x cheaper than INTER_AREA on a 1088x1920 frame (0.6 vs 7.5 ms)
            small = cv2.resize(img, (W, H), interpolation=cv2.INTER_LINEAR) if W < img.shape[1] else img
            ok, jpg = cv2.imencode(".jpg", small, [cv2.IMWRITE_JPEG_QUALITY, int(self.cfg.jpeg_quality)])
            if not ok:
                continue
            head = json.dumps(
                {
                    "cam": cam,
                    "seq": self.seq,
                    "frame": int(fs.index),
                    "t_capture_ms": t_cap_ms,
                    "w": W,
                    "h": H,
                    "src_wh": [w, h],
                }
            ).encode()
            out[f"img:{cam}"] = len(head).to_bytes(2, "big") + head + jpg.tobytes()
            self.images_sent += 1
        return out

    def hello(self) -> dict[str, Any]:
        if self._rig_data is None and self.rig is not None:  # once: the cameras do not move
            try:
                self._rig_data = {"cameras": rig_cameras_data(self.rig)}
            except Exception:  # noqa: BLE001 - a page without the camera drawings still works
                log.exception("live view: rig drawing data")
        rig = self._rig_data
        return {
            "type": "hello",
            "cameras": list(self.cameras),
            "rig": rig,
            "joint_names": list(CANONICAL.joint_names),
            "parents": list(CANONICAL.parents),
            "hand_names": list(HAND2D),
            "hand_parents": list(HAND2D_PARENTS),
            "fps": max(c.fps or 30.0 for c in self.capture.cameras),
            "image_hz": self.cfg.image_hz,
            "forecast": None if self.forecast is None else {"on": self.forecast.enabled},
        }

    def _camera_stats(self) -> dict[str, dict[str, Any]]:
        out: dict[str, dict[str, Any]] = {}
        grabbers = getattr(self.recorder, "grabbers", {}) or {}
        now = time.monotonic()
        for cam in self.cameras:
            g = grabbers.get(cam)
            if g is None:
                out[cam] = {"fps": None, "frames": 0, "dropped": 0}
                continue
            st = g.stats
            n = int(st.frames)
            # None ("–" on the page) until a second of frames is counted: not a camera that gives 0 fps
            t_prev, n_prev, fps = self._fps.get(cam, (now, n, None))
            if now - t_prev >= 1.0:
                fps = (n - n_prev) / (now - t_prev)
                t_prev, n_prev = now, n
            self._fps[cam] = (t_prev, n_prev, fps)
            dq = dict(st.dropped_queue)
            out[cam] = {
                "fps": None if fps is None else round(fps, 1),
                "frames": n,
                "dropped": int(dq.get("writer", 0)) + int(st.dropped_source),
                "dropped_live": int(dq.get("live", 0)),
            }
        return out

    def state(self, step: LiveStep, t_cap_ms: float) -> dict[str, Any]:
        fs = step.frameset
        est = step.outputs.get("tracks")
        tracks = []
        shown: list[tuple[int, np.ndarray]] = []  # (track id, xyz (J,3)) of the tracks present
        hshown: list[tuple[int, np.ndarray]] = []  # (track id, (44,3) wrists and hands) where a hand is known
        if est is not None:
            ids = np.asarray(est.track_id).reshape(-1)
            names = getattr(est, "joint_names", None)
            names = CANONICAL.joint_names if names is None else tuple(names)
            J = len(names) if not len(ids) else -1  # an empty room: (0, J, 3), not (0, -1, 3)
            xyz = np.asarray(est.xyz_m, np.float64).reshape(len(ids), J, 3)
            std = np.asarray(est.std_m, np.float64).reshape(len(ids), J)
            hx = None
            if names != CANONICAL.joint_names:  # a whole body: the body19 joints by name, the hands apart
                hx = _by_name(xyz, names, HAND2D) if all(n in names for n in HANDS) else None
                xyz = _by_name(xyz, names, CANONICAL.joint_names)
                std = _by_name(std[..., None], names, CANONICAL.joint_names)[..., 0]
            for k, tid in enumerate(ids):
                if not np.isfinite(xyz[k]).all(-1).any():
                    continue
                shown.append((int(tid), xyz[k]))
                tr = {"id": int(tid), "xyz": _flat(xyz[k], 3), "std": _flat(std[k], 3)}
                if hx is not None and np.isfinite(hx[k, 2:]).all(-1).any():
                    tr["hands"] = _flat(hx[k], 3)
                    hshown.append((int(tid), hx[k]))
                tracks.append(tr)
        det: dict[str, list[list[float | None]]] = {}
        proj: dict[str, list[Any]] = {}
        hdet: dict[str, list[list[float | None]]] = {}
        hproj: dict[str, list[Any]] = {}
        dets = step.outputs.get("detections") or {}
        for cam in self.cameras:
            d = dets.get(cam)
            if d is not None and len(getattr(d, "xy_px", ())):
                xy = np.asarray(d.xy_px, np.float64)
                skel = getattr(d, "skeleton", CANONICAL.id)
                names2d = get_skeleton(skel).joint_names
                if all(n in names2d for n in HANDS):
                    hxy = _by_name(xy, names2d, HAND2D)
                    hdet[cam] = [_flat(h) for h in hxy if np.isfinite(h[2:]).all(-1).any()]
                if skel != CANONICAL.id:
                    xy, _ = convert(xy, np.asarray(d.score), skel, CANONICAL)
                det[cam] = [_flat(p) for p in xy]
            if self.rig is not None and shown and cam in self.rig.names:
                uv = self.rig[cam].project(np.concatenate([x for _, x in shown])).reshape(len(shown), -1, 2)
                proj[cam] = [[tid, _flat(uv[k])] for k, (tid, _) in enumerate(shown)]
            if self.rig is not None and hshown and cam in self.rig.names:
                uv = self.rig[cam].project(np.concatenate([x for _, x in hshown])).reshape(len(hshown), -1, 2)
                hproj[cam] = [[tid, _flat(uv[k])] for k, (tid, _) in enumerate(hshown)]
        live: dict[str, Any] = {}
        if self.runner is not None:
            s = self.runner.stats
            lat = s.latency_ms[-60:]
            live = {
                "processed": s.processed,
                "skipped": s.skipped,
                "latency_ms": round(float(np.median(lat)), 1) if lat else None,
                "errors": dict(s.errors),
                "jumps": len(s.jumps),
                # "the clock jumped N times (...): a new track segment", or None
                "jumps_line": jump_line(s.jumps)[2:] or None,
            }
        return {
            "type": "state",
            "seq": self.seq,
            "frame": int(fs.index),
            "t_ns": int(fs.t_ns),
            "t_capture_ms": t_cap_ms,
            "t_sent_ms": host_now_ns() / 1e6,
            "tracks": tracks,
            "det": det,
            "proj": proj,
            "cameras": self._camera_stats(),
            "live": live,
            "view": {"clients": len(self._clients), "dropped_updates": self.dropped_updates},
            "forecast": self._forecast_state(int(fs.t_ns)),
            **({"hdet": hdet} if hdet else {}),
            **({"hproj": hproj} if hproj else {}),
        }

    def _forecast_state(self, now_ns: int) -> dict[str, Any] | None:
        """The forecast to draw (None: the view has no forecaster): per track its path on the floor and
        its ghost pose at the horizon, and what it costs."""
        if self.forecast is None:
            return None
        d = self.forecast.view_data(now_ns)
        d["tracks"] = [
            {"id": t["id"], "path": _flat(t["path"], 3), "ghost": _flat(t["ghost"], 3)} for t in d["tracks"]
        ]
        return d

    def status(self) -> dict[str, Any]:
        lat = self.latency_ms()
        return {
            "clients": self.n_clients,
            "clients_seen": self.clients_seen,
            "states_sent": self.states_sent,
            "images_sent": self.images_sent,
            "dropped_updates": self.dropped_updates,
            "latency_ms_median": float(np.median(lat)) if lat else None,
            "acks": len(lat),
            "producer_cpu_s": self.encode_s,
        }
