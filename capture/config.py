"""``cams.yaml``: the capture configuration, validated once into typed frozen dataclasses.

The minimal file every script may rely on::

    cameras:
      - name: cam01
        source: /path/to/cam01.mp4   # also usb:0, /dev/video0, rtsp://..., oak:<mxid>, synthetic:
      - name: cam02
        source: /path/to/cam02.mp4

The full schema (every key optional except ``cameras[].name`` and ``cameras[].source``)::

    schema: cams/1                 # optional tag
    out: sessions/today            # output folder (``capture-run --out`` overrides it)
    calibration: calib/rig.toml    # rig this session refers to (written into session.toml)
    defaults:                      # per-camera keys applied where a camera leaves them out
      fps: 30
    cameras:
      - name: cam01                # stable name: [A-Za-z0-9_-], unique; the file names use it
        source: rtsp://user:pw@10.0.0.5/stream   # credentials are never logged or written
        resolution: [1920, 1080]   # width, height in px (null = what the source gives)
        fps: 30                    # requested frame rate (null = what the source gives)
        exposure_us: null          # manual exposure in microseconds (null = auto)
        codec: mp4v                # mp4v | mjpg | xvid (host encoders); h264 | h265 | mjpeg (on-device, OAK;
                                   # mjpeg: JPEGs the live loop decodes where it takes a frame)
        quality: 80                # encoder quality 1..100 (mjpg)
        loop: false                # file replay: start again at the end
        realtime: true             # file replay: pace frames by their timestamps
        drop_late: false           # file replay: behave like a camera on a slow host (drop late frames
                                   # and never wait for the writer); false = every frame is recorded
        stream_copy: true          # record compressed frames as they come (no re-encoding): a file's
                                   # h264/hevc/mpeg4/mjpeg packets, a USB camera's MJPEG (asked for);
                                   # false = decode and encode with `codec`
    sync:
      tolerance_ms: null           # frame-set tolerance (null = half a frame period)
      max_wait_ms: 200             # emit an incomplete set after this long
    recorder:
      segment_s: 0.5               # video segment length: a kill loses at most this much
      queue_frames: 64             # bounded per-camera queue (frames beyond it are dropped and counted)
      min_free_mb: 500             # disk-space guard: stop cleanly below this much free space
      reconnect_initial_s: 0.1     # reconnect backoff (doubles up to reconnect_max_s)
      reconnect_max_s: 2.0
      reconnect_give_up_s: 60      # stop retrying a camera after this long (0 = never give up)
    live:
      enabled: false               # same as --live
      stages: [keypoints, triangulate, track]
      every_n: 1                   # process every n-th frame set
      preset: ""                   # the 2D preset (as [keypoints] preset; "" = the default)
      decode_reduce: 0             # JPEG frames (MJPEG cameras/files) decoded for the 2D at 1/n size: 1, 2,
                                   # 4, 8; 0 = auto (the largest keeping the long side >= 720 px)
      forecast: true               # with --view: the forecast on the page (false = --no-forecast)

Sources: ``usb:<index>``, ``/dev/videoN``, ``rtsp://``/``rtsps://``/``http(s)://`` streams,
``oak:`` (first OAK device) or ``oak:<mxid-or-serial>[?socket=CAM_A&sync=master|slave|auto]``,
``synthetic:`` (a generated test pattern; ``synthetic:?disconnect_at_s=1&disconnect_for_s=3``
simulates a cable pull), or a path to a video file (file replay at the file's own timestamps) or a
recorded session's ``raw/<cam>``.
"""

from __future__ import annotations

import os
import re
import urllib.parse
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

from roomcap.core.config import bounded, check_keys, check_range, coerce, config_from_dict
from roomcap.core.errors import FormatError, InputError, UnknownNameError
from roomcap.core.fileio import check_schema
from roomcap.core.redact import redact as redact_url  # one redaction for every source string

CAMS_SCHEMA = "cams"
CAMS_VERSION = 1

HOST_CODECS = ("mp4v", "mjpg", "xvid")
DEVICE_CODECS = ("h264", "h265", "mjpeg")  # an OAK's on-device encoders (mjpeg: each frame a JPEG)
CODECS = HOST_CODECS + DEVICE_CODECS
SOURCE_KINDS = ("file", "usb", "device", "rtsp", "oak", "synthetic")
LIVE_STAGES = ("keypoints", "triangulate", "track")
_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_\-]{0,63}$")


class ConfigError(FormatError):
    """cams.yaml holds an unknown key or an impossible value."""


# ----------------------------------------------------------------------------- credentials


def source_kind(source: str) -> str:
    """Classify a ``source`` string into one of SOURCE_KINDS (no I/O)."""
    s = source.strip()
    low = s.lower()
    if low.startswith("usb:"):
        return "usb"
    if low.startswith("/dev/video"):
        return "device"
    if low.startswith(("rtsp://", "rtsps://", "http://", "https://", "rtmp://", "udp://", "tcp://")):
        return "rtsp"
    if low == "oak" or low.startswith("oak:"):
        return "oak"
    if low == "synthetic" or low.startswith("synthetic:"):
        return "synthetic"
    return "file"


# ----------------------------------------------------------------------------- source options

OAK_SYNC_ROLES = ("off", "auto", "master", "slave")
OAK_SOCKETS = ("CAM_A", "CAM_B", "CAM_C", "CAM_D")


def _real(v: str) -> float:
    x = float(v)
    if x != x or x in (float("inf"), float("-inf")):
        raise ValueError(v)
    return x


def _count(v: str) -> int:
    x = int(v)
    if x < 0:
        raise ValueError(v)
    return x


def _choice(choices: tuple[str, ...], case) -> Any:
    def parse(v: str) -> str:
        v = case(v)
        if v not in choices:
            raise ValueError(v)
        return v

    parse.what = f"one of {list(choices)}"  # type: ignore[attr-defined]
    return parse


_real.what = "a finite number"  # type: ignore[attr-defined]
_count.what = "a whole number >= 0"  # type: ignore[attr-defined]

# the ``?key=value&...`` options each kind of source takes (the only parser of them: cams.yaml's check,
# parse_config, and the sources when recording)
SOURCE_OPTIONS: dict[str, dict[str, Any]] = {
    "synthetic": {
        "offset_ms": _real,
        "drift_ppm": _real,
        "disconnect_at_s": _real,
        "disconnect_for_s": _real,
        "frames": _count,
        "drop_every": _count,
    },
    "oak": {"socket": _choice(OAK_SOCKETS, str.upper), "sync": _choice(OAK_SYNC_ROLES, str.lower)},
}


class SourceOptionError(InputError, ValueError):
    """A ``?key=value`` option of a source that no recording would accept (the message says which)."""


def source_options(source: str, kind: str | None = None) -> dict[str, Any]:
    """The ``?key=value&...`` options of a ``synthetic:`` or ``oak:`` source, parsed and checked (other
    kinds: ``{}``; a URL's query belongs to the stream). Raises :class:`SourceOptionError` naming the
    option and the valid ones.

    >>> source_options("synthetic:?frames=5&offset_ms=2.5")
    {'frames': 5, 'offset_ms': 2.5}
    """
    kind = kind or source_kind(source)
    spec = SOURCE_OPTIONS.get(kind)
    if spec is None:
        return {}
    query = source.partition("?")[2]
    try:
        pairs = urllib.parse.parse_qsl(query, keep_blank_values=True, strict_parsing=bool(query))
    except ValueError:
        raise SourceOptionError(f"{kind} options {query!r} are not key=value pairs joined by '&'.") from None
    out: dict[str, Any] = {}
    bad = sorted({k for k, _ in pairs} - set(spec))
    if bad:
        raise SourceOptionError(f"unknown {kind} option(s) {bad}; valid: {list(spec)}.")
    for k, v in pairs:
        if k in out:
            raise SourceOptionError(f"{kind} option {k!r} is given twice.")
        try:
            out[k] = spec[k](v)
        except ValueError:
            raise SourceOptionError(f"{kind} option {k}={v!r} must be {spec[k].what}.") from None
    return out


# ----------------------------------------------------------------------------- dataclasses


@dataclass(frozen=True)
class CameraConfig:
    name: str
    source: str = field(repr=False)  # may hold credentials: never print it, use .source_redacted
    resolution: tuple[int, int] | None = None  # (width, height) px
    fps: float | None = None
    exposure_us: int | None = None
    codec: str = "mp4v"
    quality: int = 80
    loop: bool = False
    realtime: bool = True
    drop_late: bool = False
    stream_copy: bool = True  # file replay: write the file's packets as they are (capture.streamcopy)

    @property
    def kind(self) -> str:
        return source_kind(self.source)

    @property
    def source_redacted(self) -> str:
        return redact_url(self.source)

    def __repr__(self) -> str:
        return (
            f"CameraConfig(name={self.name!r}, source={self.source_redacted!r}, resolution={self.resolution},"
            f" fps={self.fps}, codec={self.codec!r})"
        )

    def to_dict(self) -> dict[str, Any]:
        """For session.toml: credentials redacted, None left out."""
        d = {f.name: getattr(self, f.name) for f in fields(self)}
        d["source"] = self.source_redacted
        d["kind"] = self.kind
        if d["resolution"] is not None:
            d["resolution"] = list(d["resolution"])
        return {k: v for k, v in d.items() if v is not None}


@dataclass(frozen=True)
class SyncConfig:
    tolerance_ms: float | None = bounded(None, 0.01, 10_000)  # None = half a frame period
    max_wait_ms: float = bounded(200.0, 1, 60_000)

    def tolerance_ns(self, fps: float) -> int:
        if self.tolerance_ms is not None:
            return int(round(self.tolerance_ms * 1e6))
        return int(round(0.5e9 / fps))


@dataclass(frozen=True)
class RecorderConfig:
    segment_s: float = bounded(0.5, 0.1, 3600)
    queue_frames: int = bounded(64, 2, 100_000)
    min_free_mb: float = bounded(500.0, 0, 1e9)
    reconnect_initial_s: float = bounded(0.1, 0.001, 60)
    reconnect_max_s: float = bounded(2.0, 0.001, 600)
    reconnect_give_up_s: float = bounded(60.0, 0, 1e7)


DECODE_REDUCE = (0, 1, 2, 4, 8)  # live.decode_reduce: auto, or libjpeg's scale factors
DECODE_REDUCE_MIN_SIDE = 720  # auto: the largest factor that keeps a frame's long side at least this (px)


def auto_reduce(width: int, height: int, setting: int = 0) -> int:
    """The factor a JPEG frame of ``width`` x ``height`` is decoded at for the 2D stage: ``setting`` when
    given (1, 2, 4, 8), else the largest that keeps the long side >= ``DECODE_REDUCE_MIN_SIDE`` px
    (1088x1920: 2; 1280x720: 1). The detector sees 416 px and the pose model 192 px crops, cut from a
    pyramid when they shrink more than 2x (keypoints.pipeline), so a 960 px frame loses them nothing
    a full one gives.

    >>> auto_reduce(1088, 1920), auto_reduce(1280, 720), auto_reduce(3840, 2160), auto_reduce(1088, 1920, 4)
    (2, 1, 4, 4)
    """
    if setting:
        return setting
    r = 1
    while r < 8 and max(width, height) / (2 * r) >= DECODE_REDUCE_MIN_SIDE:
        r *= 2
    return r


@dataclass(frozen=True)
class LiveConfig:
    enabled: bool = False
    stages: tuple[str, ...] = LIVE_STAGES
    every_n: int = bounded(1, 1, 10_000)
    preset: str = ""  # the 2D stage's preset, as [keypoints] preset of a pipeline TOML ("" = the default)
    # JPEG frames decoded for the 2D stage at 1/decode_reduce of their size (1, 2, 4, 8; 0 = auto:
    # DECODE_REDUCE_MIN_SIDE); keypoints are mapped back to full-size pixels
    decode_reduce: int = bounded(0, 0, 8)
    forecast: bool = True  # with --view: each tracked person's next seconds on the page (--no-forecast)


@dataclass(frozen=True)
class CaptureConfig:
    cameras: tuple[CameraConfig, ...]
    out: str | None = None
    calibration: str | None = None
    sync: SyncConfig = SyncConfig()
    recorder: RecorderConfig = RecorderConfig()
    live: LiveConfig = LiveConfig()
    path: str | None = None  # where it was read from (not a yaml key)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(c.name for c in self.cameras)

    def camera(self, name: str) -> CameraConfig:
        for c in self.cameras:
            if c.name == name:
                return c
        raise UnknownNameError(f"no camera {name!r}; cameras are {list(self.names)}")

    def to_dict(self) -> dict[str, Any]:
        """The configuration as written into session.toml (credentials redacted)."""
        out: dict[str, Any] = {
            "schema": f"{CAMS_SCHEMA}/{CAMS_VERSION}",
            "cameras": [c.to_dict() for c in self.cameras],
        }
        if self.out:
            out["out"] = self.out
        if self.calibration:
            out["calibration"] = self.calibration
        for name in ("sync", "recorder", "live"):
            sub = getattr(self, name)
            d = {f.name: getattr(sub, f.name) for f in fields(sub)}
            out[name] = {k: (list(v) if isinstance(v, tuple) else v) for k, v in d.items() if v is not None}
        return out


# ----------------------------------------------------------------------------- parsing

_TOP_KEYS = ("schema", "out", "calibration", "defaults", "cameras", "sync", "recorder", "live")
_CAM_KEYS = tuple(f.name for f in fields(CameraConfig))


def _reject_unknown(d: dict, valid: tuple[str, ...], where: str, path) -> None:
    check_keys(d, valid, where, path, error=ConfigError)


def _num(v: Any, where: str, path, lo: float, hi: float, integer: bool = False, allow_none: bool = False):
    return check_range(v, where, path, lo, hi, integer=integer, allow_none=allow_none, error=ConfigError)


def _bool(v: Any, where: str, path) -> bool:
    return bool(coerce(v, bool, where, path, ConfigError))


def _camera_source(source: Any, where: str, path) -> tuple[str, str]:
    """A camera's source checked (a file made absolute beside cams.yaml) and its kind."""
    if isinstance(source, int) and not isinstance(source, bool):
        source = f"usb:{source}"
    if not isinstance(source, str) or not source.strip():
        raise ConfigError(
            path,
            f"{where}.source",
            "missing or empty.",
            "Give a video file, usb:<index>, /dev/videoN, rtsp://..., oak:<mxid> or synthetic:.",
        )
    source = source.strip()
    kind = source_kind(source)
    if kind == "usb" and not source[4:].strip().isdigit():
        raise ConfigError(
            path, f"{where}.source", f"{source!r}: usb:<index> needs a non-negative integer index."
        )
    try:
        source_options(source, kind)  # the options recording will take, checked the same way
    except SourceOptionError as e:
        raise ConfigError(path, f"{where}.source", str(e)) from None
    if kind == "file":
        p = Path(os.path.expanduser(source))
        if not p.is_absolute() and path is not None:
            p = Path(path).resolve().parent / p
        source = str(p)
    return source, kind


def _camera_resolution(res: Any, where: str, path) -> tuple[int, int] | None:
    """A camera's ``[width, height]`` (or ``"WxH"``) checked, or None when not set."""
    if res is not None:
        if isinstance(res, str) and re.fullmatch(r"\d+x\d+", res):
            res = [int(x) for x in res.split("x")]
        if not (isinstance(res, (list, tuple)) and len(res) == 2):
            raise ConfigError(path, f"{where}.resolution", f"expected [width, height], got {res!r}.")
        res = (
            _num(res[0], f"{where}.resolution[0]", path, 16, 16384, True),
            _num(res[1], f"{where}.resolution[1]", path, 16, 16384, True),
        )
    return res


def _camera_codec(codec: Any, kind: str, where: str, path) -> str:
    """A camera's codec checked against the codecs its kind of source can write, lower case."""
    if not isinstance(codec, str) or codec.lower() not in CODECS:
        raise ConfigError(
            path, f"{where}.codec", f"unknown codec {codec!r}.", f"Valid codecs: {list(CODECS)}."
        )
    codec = codec.lower()
    if codec in DEVICE_CODECS and kind != "oak":
        raise ConfigError(
            path,
            f"{where}.codec",
            f"{codec} is encoded on the device and only OAK cameras have an encoder.",
            f"Use one of {list(HOST_CODECS)} for {kind} sources.",
        )
    return codec


def _camera(raw: Any, i: int, defaults: dict, path) -> CameraConfig:
    """The ``cameras[i]`` entry of cams.yaml (with the file's camera defaults) checked."""
    where = f"cameras[{i}]"
    if not isinstance(raw, dict):
        raise ConfigError(path, where, f"expected a mapping with name and source, got {type(raw).__name__}.")
    _reject_unknown(raw, _CAM_KEYS, where, path)
    d = {**defaults, **raw}
    name = d.get("name")
    if not isinstance(name, str) or not _NAME_RE.match(name):
        raise ConfigError(
            path,
            f"{where}.name",
            f"{name!r} is not a valid camera name.",
            "Use 1-64 characters from A-Z a-z 0-9 _ - (it names the files), e.g. cam01.",
        )
    where = f"cameras[{i}] ({name})"
    source, kind = _camera_source(d.get("source"), where, path)
    res = _camera_resolution(d.get("resolution"), where, path)
    fps = _num(d.get("fps"), f"{where}.fps", path, 0.1, 1000.0, allow_none=True)
    exposure = _num(d.get("exposure_us"), f"{where}.exposure_us", path, 1, 10_000_000, True, allow_none=True)
    if exposure is not None and fps is not None and exposure > 1e6 / fps:
        raise ConfigError(
            path,
            f"{where}.exposure_us",
            f"{exposure} us is longer than one frame at {fps} fps ({1e6 / fps:.0f} us).",
            "Shorten the exposure or lower the fps.",
        )
    codec = _camera_codec(d.get("codec", "mp4v"), kind, where, path)
    quality = _num(d.get("quality", 80), f"{where}.quality", path, 1, 100, True)
    return CameraConfig(
        name=name,
        source=source,
        resolution=res,
        fps=fps,
        exposure_us=exposure,
        codec=codec,
        quality=quality,
        loop=_bool(d.get("loop", False), f"{where}.loop", path),
        realtime=_bool(d.get("realtime", True), f"{where}.realtime", path),
        drop_late=_bool(d.get("drop_late", False), f"{where}.drop_late", path),
        stream_copy=_bool(d.get("stream_copy", True), f"{where}.stream_copy", path),
    )


def _section(raw: Any, cls, where: str, path) -> Any:
    """A section (sync, recorder, live) by the core loader: keys, kinds and the fields' ranges checked."""
    if raw is None:
        return cls()
    if not isinstance(raw, dict):
        raise ConfigError(path, where, f"expected a mapping, got {type(raw).__name__}.")
    return config_from_dict(cls, raw, where, path, error=ConfigError)


def shared_sources(cfg: CaptureConfig) -> list[str]:
    """One sentence per group of cameras that read the same file, stream or synthetic source (devices
    opened twice are refused by :func:`parse_config`): they record the same frames twice and their skew
    (0.00 ms) says nothing about the cameras."""
    groups: dict[str, list[str]] = {}
    for c in cfg.cameras:
        key = os.path.realpath(c.source) if c.kind == "file" else c.source
        groups.setdefault(key, []).append(c.name)
    return [
        f"cameras {', '.join(repr(n) for n in names)} all read {cfg.camera(names[0]).source_redacted!r}: "
        "the same frames would be recorded twice and the skew between them says nothing about the cameras. "
        "Give each camera its own source in cams.yaml."
        for names in groups.values()
        if len(names) > 1
    ]


def parse_config(data: Any, path: str | os.PathLike | None = None) -> CaptureConfig:
    """Validate a parsed cams.yaml mapping into a CaptureConfig (raises ConfigError)."""
    if not isinstance(data, dict):
        raise ConfigError(
            path,
            None,
            f"expected a mapping with a 'cameras' list, got {type(data).__name__}.",
            "See capture/config.py for the schema.",
        )
    _reject_unknown(data, _TOP_KEYS, "<top level>", path)
    if "schema" in data:
        check_schema(data["schema"], CAMS_SCHEMA, (CAMS_VERSION,), path)
    defaults = data.get("defaults") or {}
    if not isinstance(defaults, dict):
        raise ConfigError(path, "defaults", "expected a mapping of per-camera keys.")
    _reject_unknown(defaults, tuple(k for k in _CAM_KEYS if k not in ("name", "source")), "defaults", path)
    cams_raw = data.get("cameras")
    if not isinstance(cams_raw, list) or not cams_raw:
        raise ConfigError(
            path,
            "cameras",
            "missing or empty; at least one camera is needed.",
            "Add a list of {name, source} entries.",
        )
    cams = tuple(_camera(c, i, defaults, path) for i, c in enumerate(cams_raw))
    seen: dict[str, int] = {}
    for i, c in enumerate(cams):
        if c.name in seen:
            raise ConfigError(
                path,
                f"cameras[{i}].name",
                f"camera name {c.name!r} is used twice (cameras[{seen[c.name]}] and cameras[{i}]).",
                "Give every camera a unique name.",
            )
        seen[c.name] = i
    srcs: dict[str, str] = {}
    for c in cams:
        if c.kind in ("usb", "device", "oak") and c.source in srcs and c.source not in ("oak", "oak:"):
            raise ConfigError(
                path,
                "cameras",
                f"cameras {srcs[c.source]!r} and {c.name!r} both open "
                f"{c.source_redacted!r}; a device can be opened once.",
                "Give each camera its own source.",
            )
        srcs[c.source] = c.name
    sync = _section(data.get("sync"), SyncConfig, "sync", path)
    rec = _section(data.get("recorder"), RecorderConfig, "recorder", path)
    live_raw = data.get("live")
    if isinstance(live_raw, dict) and "stages" in live_raw:
        stages = live_raw["stages"]
        if not isinstance(stages, list) or any(s not in LIVE_STAGES for s in stages):
            raise ConfigError(
                path,
                "live.stages",
                f"{stages!r} is not a list of stages.",
                f"Valid stages: {list(LIVE_STAGES)}.",
            )
        live_raw = {**live_raw, "stages": tuple(stages)}
    live = _section(live_raw, LiveConfig, "live", path)
    if live.decode_reduce not in DECODE_REDUCE:
        raise ConfigError(
            path,
            "live.decode_reduce",
            f"{live.decode_reduce!r} is not one of {list(DECODE_REDUCE)}.",
            "0 = auto; 1, 2, 4, 8 = decode JPEG frames at 1/n of their size for the 2D stage.",
        )
    for key in ("out", "calibration"):
        if data.get(key) is not None and not isinstance(data[key], str):
            raise ConfigError(path, key, f"expected a path string, got {data[key]!r}.")
    calibration = data.get("calibration")
    if calibration and path is not None and not Path(calibration).is_absolute():
        calibration = str(Path(path).resolve().parent / calibration)
    return CaptureConfig(
        cameras=cams,
        out=data.get("out"),
        calibration=calibration,
        sync=sync,
        recorder=rec,
        live=live,
        path=None if path is None else str(path),
    )


def load_config(path: str | os.PathLike) -> CaptureConfig:
    """Read and validate a cams.yaml."""
    import yaml

    path = Path(path)
    if not path.exists():
        raise ConfigError(
            path, None, "file does not exist.", "Pass --cameras with the path of your cams.yaml."
        )
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
    except yaml.YAMLError as e:
        raise ConfigError(path, None, f"is not valid YAML ({redact_url(str(e))}).") from None
    return parse_config(data, path)
