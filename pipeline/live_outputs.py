"""What ``capture-run --live`` sends out while it records: the live view, LSL/OSC streams, a Rerun file.

::

    capture-run --cameras cams.yaml --out DIR --live [--view [--view-port 8765] [--view-host HOST]
                [--no-forecast]]
                [--stream lsl,osc [--osc-to HOST:PORT] [--slots 16]] [--rerun FILE.rrd]

Each output is fed from the live loop's ``on_step`` (:class:`roomcap.capture.live.LiveRunner`) after the
stages ran on a frame set, and never makes it wait:

- the view (:mod:`roomcap.pipeline.liveview`) takes the step into a latest-value slot; its own thread encodes
  and pushes, dropping updates a slow page cannot take;
- the forecast drawn on the view (:mod:`roomcap.pipeline.live_forecast`, on with ``--view`` and a track
  stage unless ``--no-forecast`` or ``live: {forecast: false}``) takes the step's tracks into a short
  history; its own thread forecasts from the newest;
- the streams (:class:`roomcap.outputs.lsl_osc.TrackStreamer`) send UDP datagrams and LSL samples, which do
not
  wait for a reader;
- the Rerun recording (:class:`roomcap.outputs.rerun_recording.LiveRerun`) is written by its own thread from a
  bounded queue (a full queue drops the frame set for the file, counted).

An output that fails while recording is logged once and left out; the recording goes on. Bad options
(a view host other than loopback without a token, a port in use, a package missing) stop the command
before anything is recorded, with exit 2 and a message saying what to do.
"""

from __future__ import annotations

import argparse
import logging
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from roomcap.calibrate.camera import CameraRig
from roomcap.capture.config import CaptureConfig
from roomcap.capture.live import LiveRunner, LiveStep
from roomcap.core.cli import positive_int
from roomcap.core.errors import InputError
from roomcap.keypoints.skeletons import CANONICAL
from roomcap.outputs.lsl_osc import StreamConfig, TrackStreamer, parse_host_port, parse_kinds

# the page's server (aiohttp), the Rerun writer and the forecaster are imported when asked for (--view,
# --rerun): capture-run starts the cameras sooner without them
if TYPE_CHECKING:
    from roomcap.pipeline.live_forecast import LiveForecast
    from roomcap.pipeline.liveview.server import LiveView

DEFAULT_PORT = 8765  # the live view's port (roomcap.pipeline.liveview.server.DEFAULT_PORT, checked by a test)

log = logging.getLogger(__name__)
J = CANONICAL.n_joints


def load_rig(cfg: CaptureConfig) -> CameraRig | None:
    """The calibration cams.yaml names (relative to cams.yaml), None when it names none or it cannot be
    read (logged: live keeps recording without 3D)."""
    if not cfg.calibration:
        return None
    p = Path(cfg.calibration)
    if not p.is_absolute() and cfg.path:
        p = Path(cfg.path).parent / p
    try:
        return CameraRig.load(p)
    except Exception as e:  # noqa: BLE001 - live keeps recording without 3D
        log.warning("live: cannot load calibration %s (%s); 3D stages are off", cfg.calibration, e)
        return None


class Outputs:
    """:class:`roomcap.capture.live.LiveOutputs` of ``capture-run``: the options and the outputs they open
    (``feed``: the :class:`StepFeed` of the last :meth:`open`, None when nothing was asked for)."""

    feed: StepFeed | None = None

    def add_arguments(self, parser: argparse.ArgumentParser) -> None:
        g = parser.add_argument_group("sent out while recording (with --live)")
        g.add_argument("--view", action="store_true", help="serve the live view page (default: off)")
        g.add_argument(
            "--view-port",
            type=int,
            default=DEFAULT_PORT,
            help=f"port of the live view (default {DEFAULT_PORT}; 0 = any free port)",
        )
        g.add_argument(
            "--view-host",
            default="127.0.0.1",
            help="address the view listens on (default 127.0.0.1, this machine only); any other address "
            "needs --view-token",
        )
        g.add_argument(
            "--view-token",
            default=None,
            help="token the page's URL must carry (needed with a --view-host other than loopback; 'auto': "
            "a random one, printed once; default: none)",
        )
        g.add_argument(
            "--no-forecast",
            action="store_true",
            help="do not forecast on the live view (default: each tracked person's next 1.5 s from the "
            "shipped forecaster, drawn on the page, which can switch it off; also live: {forecast: false} "
            "in cams.yaml)",
        )
        g.add_argument(
            "--stream",
            action="append",
            default=None,
            metavar="KINDS",
            help="lsl, osc or lsl,osc (repeatable): every frame set's tracks to the Lab Streaming Layer "
            "and/or OSC (default: none)",
        )
        g.add_argument(
            "--osc-to",
            default=None,
            metavar="HOST:PORT",
            help="OSC receiver (needed by --stream osc; default: none)",
        )
        g.add_argument(
            "--slots",
            type=positive_int,
            default=16,
            help="LSL: person slots in the channel layout (default 16)",
        )
        g.add_argument(
            "--rerun",
            type=Path,
            default=None,
            metavar="FILE.rrd",
            help="also write a Rerun recording (default: none)",
        )

    def open(self, args: argparse.Namespace, runner: LiveRunner | None, recorder: Any) -> Callable[[], None]:
        kinds = parse_kinds(args.stream)
        wanted = [n for n, on in (("--view", args.view), ("--stream", kinds), ("--rerun", args.rerun)) if on]
        if not wanted:
            return lambda: None
        if runner is None:
            raise InputError(f"{', '.join(wanted)} need --live (they send what the live stages make).")
        cfg = runner.cfg
        fps = max(c.fps or 30.0 for c in cfg.cameras)
        osc_to = parse_host_port(args.osc_to) if args.osc_to else None
        scfg = StreamConfig(kinds, osc_to, args.slots, session=runner.layout.root.name) if kinds else None
        view = rerun = streamer = forecast = None
        rig = load_rig(cfg) if args.view or args.rerun else None
        rig = rig.subset(list(cfg.names)) if rig is not None else None
        closers: list[Callable[[], None]] = []
        try:
            if args.view:
                if (
                    cfg.live.forecast
                    and not getattr(args, "no_forecast", False)
                    and "track" in runner.planned
                ):
                    from roomcap.pipeline.live_forecast import LiveForecast

                    forecast = LiveForecast()
                    forecast.start()  # loads the model on its own thread
                    closers.append(forecast.stop)
                    runner.reports.append(forecast.summary_line)
                from roomcap.pipeline.liveview.server import LiveView, ViewConfig

                vcfg = ViewConfig(host=args.view_host, port=args.view_port, token=args.view_token)
                view = LiveView(vcfg, cfg, runner, recorder, rig, forecast)
                view.start()  # binds now: a port in use or a refused host fails here
                closers.append(view.stop)
                print(f"live view: {view.url}", flush=True)
            if scfg is not None:
                streamer = TrackStreamer(scfg, fps)
                closers.append(streamer.close)
                where = [
                    k if k != "osc" or osc_to is None else f"osc to {osc_to[0]}:{osc_to[1]}" for k in kinds
                ]
                log.info("streaming tracks: %s", ", ".join(where))
            if args.rerun is not None:
                from roomcap.outputs.rerun_recording import LiveRerun

                rerun = LiveRerun(args.rerun, runner.layout, rig)
                closers.append(rerun.close)
        except BaseException:
            for c in reversed(closers):
                c()
            raise
        feed = self.feed = StepFeed(view, streamer, rerun, forecast)
        previous = runner.on_step

        def on_step(step: LiveStep) -> None:
            if previous is not None:
                previous(step)
            feed(step)

        runner.on_step = on_step

        def close() -> None:
            for c in reversed(closers):
                try:
                    c()
                except Exception:  # noqa: BLE001 - the recording is done; say what did not close
                    log.exception("closing a live output failed")
            if feed.n:
                log.info("live outputs: %s", feed.summary())

        return close


class StepFeed:
    """Hands one live step to each open output; times what that costs the live loop."""

    def __init__(
        self,
        view: LiveView | None,
        streamer: TrackStreamer | None,
        rerun: Any = None,
        forecast: LiveForecast | None = None,
    ):
        self.view, self.streamer, self.rerun, self.forecast = view, streamer, rerun, forecast
        self.n = 0
        self.cpu_s = 0.0
        self.failed: set[str] = set()

    def __call__(self, step: LiveStep) -> None:
        t0 = time.thread_time()
        self.n += 1
        if self.forecast is not None:
            self.forecast.offer(step)
        if self.view is not None:
            self.view.offer(step)
        est = step.outputs.get("tracks")
        if self.streamer is not None:
            # every processed frame set is a sample, an empty room (or a set the track stage missed) too
            if est is None:
                ids, xyz, std = np.zeros(0, np.int64), np.zeros((0, J, 3)), np.zeros((0, J))
            else:
                ids, xyz, std = est.track_id, est.xyz_m, est.std_m
            try:
                self.streamer.push(step.frameset.index, step.frameset.t_ns, ids, xyz, std)
            except Exception as e:  # noqa: BLE001 - never stops the capture
                if "stream" not in self.failed:
                    log.warning("stream: %s (logged once; the recording goes on)", e)
                self.failed.add("stream")
        if self.rerun is not None:
            self.rerun.offer(step)
        self.cpu_s += time.thread_time() - t0

    def summary(self) -> str:
        return f"{self.n} frame sets, {1e3 * self.cpu_s / max(1, self.n):.2f} ms CPU each in the live loop"
