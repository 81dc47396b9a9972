"""Model descriptions, where model files live, checksums and downloads.

A model is described by a small TOML (``keypoints/models/*.toml`` ship with the
package; users add their own by dropping ``<name>.toml`` beside their ONNX files
in a model directory). A description says which file, its sha256, where to get
it, how to prepare the input (size, layout, colour order, dtype, normalisation,
crop rule) and which decoder turns the outputs into boxes/keypoints in which
skeleton layout. See ``keypoints/models/yolox_nano.toml`` for a commented example.

Model files are looked up, in order, in: the ``model_dir`` argument, the
``ROOMCAP_MODELS`` environment variable (``os.pathsep``-separated list), the
shared models folder ``$ROOMCAP_SHARED/models`` (default ``../shared/models``
beside the checkout), and the download cache ``~/.cache/roomcap/models``
(``ROOMCAP_CACHE`` overrides). ``fetch`` downloads into the cache, unpacks the
OpenMMLab SDK zip archives (``end2end.onnx``) and checks the sha256.
"""

from __future__ import annotations

import hashlib
import io
import logging
import os
import tempfile
import urllib.request
import zipfile
from dataclasses import dataclass, field
from functools import cache
from importlib import resources
from pathlib import Path
from typing import Any

from roomcap.core.config import config_from_dict
from roomcap.core.errors import FormatError, RoomcapError, UnknownNameError
from roomcap.core.fileio import atomic_path, check_schema, load_toml, save_toml, sha256_file
from roomcap.core.progress import Progress
from roomcap.keypoints.skeletons import get_skeleton

log = logging.getLogger(__name__)

SPEC_SCHEMA = "keypoint-model"
SETS_SCHEMA = "keypoint-model-sets"
# "hand": a hand landmark model on hand crops; "palm": a palm detector (keypoints.hand_model)
ROLES = ("detector", "pose", "bottomup", "onestage", "hand", "palm")
BODY_ROLES = ("pose", "bottomup", "onestage")
DECODERS = {
    "yolox": "detector",
    "dets": "detector",
    "blazepose": "pose",
    "movenet": "pose",
    "simcc": "pose",
    "rtmo": "onestage",
    "movenet_multipose": "onestage",
    "openpose": "bottomup",
    "hand_landmarks": "hand",
    "palm_ssd": "palm",
}
CROPS = ("letterbox", "affine")
REPO = Path(__file__).resolve().parents[1]


class ModelError(RoomcapError, FileNotFoundError):
    """A model file that is missing, damaged or does not match its description; says what to do."""


def _strict(cls, data: dict[str, Any], where: str):
    """Build a frozen dataclass from a dict, rejecting unknown keys with the list of valid ones."""
    try:
        return config_from_dict(cls, data, None, where)
    except TypeError as e:  # a required key missing
        raise FormatError(where, None, f"{e}.") from e


@dataclass(frozen=True)
class InputSpec:
    """How to turn an image (or a person box in it) into the model's input tensor."""

    name: str
    size_wh: tuple[int, int]
    layout: str = "NCHW"  # NCHW | NHWC
    color: str = "BGR"  # BGR | RGB
    dtype: str = "float32"  # float32 | uint8
    scale: float = 1.0  # multiply pixel values (0-255) by this first
    mean: tuple[float, float, float] = (0.0, 0.0, 0.0)  # then subtract (after scale)
    std: tuple[float, float, float] = (1.0, 1.0, 1.0)  # then divide
    crop: str = "letterbox"  # letterbox: whole image, top-left, keep aspect; affine: a person box
    pad_value: float = 0.0  # fill outside the image (0-255 scale)
    box_padding: float = 1.25  # affine: box scale factor (margin around the person)
    aspect_wh: float = 1.0  # affine: crop aspect (width / height); 1 = square

    def __post_init__(self) -> None:
        object.__setattr__(self, "size_wh", tuple(int(v) for v in self.size_wh))
        object.__setattr__(self, "mean", tuple(float(v) for v in self.mean))
        object.__setattr__(self, "std", tuple(float(v) for v in self.std))
        checks = {
            "layout": ("NCHW", "NHWC"),
            "color": ("BGR", "RGB"),
            "dtype": ("float32", "uint8"),
            "crop": CROPS,
        }
        for key, allowed in checks.items():
            if getattr(self, key) not in allowed:
                raise FormatError(
                    None, f"input.{key}", f"{getattr(self, key)!r} is not one of {list(allowed)}."
                )
        if len(self.size_wh) != 2 or min(self.size_wh) <= 0:
            raise FormatError(None, "input.size_wh", f"expected [width, height], got {self.size_wh}.")
        if len(self.mean) != 3 or len(self.std) != 3:
            raise FormatError(None, "input.mean", "mean and std need 3 values (one per channel).")

    def tensor_shape(self, batch: int | str = 1) -> tuple:
        w, h = self.size_wh
        return (batch, 3, h, w) if self.layout == "NCHW" else (batch, h, w, 3)


@dataclass(frozen=True)
class DecoderSpec:
    """Which decoder reads the outputs, and its parameters."""

    kind: str
    outputs: tuple[str, ...]
    strides: tuple[int, ...] = (8, 16, 32)  # yolox; palm_ssd: the anchor layers' strides
    class_id: int = 0  # yolox / dets: the person class
    score_threshold: float = 0.3  # detector / one-stage / palm box score
    nms_iou: float = 0.45
    n_landmarks: int = 33  # blazepose; hand_landmarks (21)
    presence_threshold: float = 0.5  # blazepose person-present probability; hand_landmarks: hand present
    split_ratio: float = 2.0  # simcc bins per input pixel
    n_joints: int = 0  # simcc (0: from the output shape)
    stride: int = 8  # openpose maps
    n_parts: int = 18  # openpose
    peak_threshold: float = 0.1  # openpose confidence-map peaks
    paf_threshold: float = 0.05  # openpose PAF line integral
    flip_test: bool = False  # top-down: also run the mirrored crop and average (measured per model)
    # top-down: drop the face points (nose, eyes, mouth) of people seen from behind (the model places them
    # with full confidence where no face is visible; keypoints.hypotheses.hide_face_from_behind)
    hide_face_from_behind: bool = False
    # top-down: how the pose model's output coordinates meet the crop's pixels. "corner": continuous
    # coordinates, pixel i spans [i, i+1) (normalised [0, 1] x size: MoveNet, BlazePose); "center": pixel i's
    # centre is at i, the convention of cv2.warpAffine that cuts the crops (mmpose's SimCC)
    pixel_coords: str = "center"
    # openpose: the (x, y) channels of each limb's PAF; () = in limb order
    paf_channels: tuple[tuple[int, int], ...] = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "outputs", tuple(self.outputs))
        object.__setattr__(self, "strides", tuple(int(s) for s in self.strides))
        object.__setattr__(self, "paf_channels", tuple(tuple(int(c) for c in p) for p in self.paf_channels))
        if self.pixel_coords not in ("center", "corner"):
            raise FormatError(
                None, "decoder.pixel_coords", f"{self.pixel_coords!r} is not 'center' or 'corner'."
            )
        if self.kind not in DECODERS:
            raise FormatError(
                None,
                "decoder.kind",
                f"unknown decoder {self.kind!r}.",
                f"Known decoders: {sorted(DECODERS)}.",
            )


@dataclass(frozen=True)
class ModelSpec:
    """One model description (``keypoints/models/<name>.toml``)."""

    name: str
    role: str
    file: str
    input: InputSpec
    decoder: DecoderSpec
    sha256: str = ""
    url: str = ""
    archive_member: str = ""
    mirrors: tuple[str, ...] = ()
    licence: str = ""
    skeleton: str = ""
    notes: str = ""
    source: str = field(default="", compare=False)  # the TOML it came from

    def __post_init__(self) -> None:
        object.__setattr__(self, "mirrors", tuple(self.mirrors))
        if self.role not in ROLES:
            raise FormatError(self.source, "role", f"{self.role!r} is not one of {list(ROLES)}.")
        if DECODERS[self.decoder.kind] != self.role:
            raise FormatError(
                self.source,
                "decoder.kind",
                f"decoder {self.decoder.kind!r} is for a {DECODERS[self.decoder.kind]}, "
                f"but the model's role is {self.role!r}.",
            )
        if self.role in BODY_ROLES:
            get_skeleton(self.skeleton)  # raises KeyError listing the known ids
        if self.sha256 and (len(self.sha256) != 64 or any(c not in "0123456789abcdef" for c in self.sha256)):
            raise FormatError(self.source, "sha256", "must be 64 lower-case hex digits or empty.")

    @property
    def urls(self) -> tuple[str, ...]:
        return tuple(u for u in (self.url, *self.mirrors) if u)

    def where_to_get(self) -> str:
        if self.urls:
            return f"Run `keypoints fetch {self.name}` (downloads {self.urls[0]})."
        return (
            f"It ships in the project's shared models folder; set ROOMCAP_MODELS or ROOMCAP_SHARED to the "
            f"folder holding {self.file}."
        )

    @classmethod
    def from_dict(cls, data: dict[str, Any], source: str = "") -> ModelSpec:
        data = dict(data)
        if "schema" in data:
            check_schema(data.pop("schema"), SPEC_SCHEMA, (1,), source)
        for key in ("input", "decoder"):
            if not isinstance(data.get(key), dict):
                raise FormatError(
                    source,
                    key,
                    f"the [{key}] table is missing.",
                    "See keypoints/models/yolox_nano.toml for an example.",
                )
        try:
            data["input"] = _strict(InputSpec, data["input"], source)
            data["decoder"] = _strict(DecoderSpec, data["decoder"], source)
        except FormatError as e:
            if e.path is None:
                raise FormatError(source, e.field, str(e).split(": ", 1)[-1]) from e
            raise
        data["source"] = source
        return _strict(cls, data, source)

    @classmethod
    def load(cls, path: str | os.PathLike) -> ModelSpec:
        return cls.from_dict(load_toml(path), str(path))


@dataclass(frozen=True)
class ModelSet:
    name: str
    pose: str
    detector: str = ""
    description: str = ""


# ----------------------------------------------------------------------------- locations


def shared_models_dir() -> Path:
    shared = os.environ.get("ROOMCAP_SHARED")
    return (Path(shared) if shared else REPO.parent / "shared") / "models"


def cache_dir() -> Path:
    env = os.environ.get("ROOMCAP_CACHE")
    return Path(env) if env else Path.home() / ".cache" / "roomcap" / "models"


def model_dirs(model_dir: str | os.PathLike | None = None) -> list[Path]:
    """Folders searched for model files and user descriptions, in order."""
    dirs: list[Path] = []
    if model_dir:
        dirs.append(Path(model_dir))
    env = os.environ.get("ROOMCAP_MODELS")
    if env:
        dirs.extend(Path(p) for p in env.split(os.pathsep) if p)
    dirs += [shared_models_dir(), cache_dir()]
    out: list[Path] = []
    for d in dirs:
        if d not in out:
            out.append(d)
    return out


# ----------------------------------------------------------------------------- descriptions


def builtin_specs() -> dict[str, ModelSpec]:
    out = {}
    for entry in resources.files("roomcap.keypoints.models").iterdir():
        if entry.name.endswith(".toml") and entry.name != "sets.toml":
            spec = ModelSpec.load(Path(str(entry)))
            out[spec.name] = spec
    return out


_builtin = cache(builtin_specs)


def list_specs(model_dir: str | os.PathLike | None = None) -> dict[str, ModelSpec]:
    """Built-in descriptions plus any ``*.toml`` with ``schema = "keypoint-model/1"`` in the model folders
    (a user description with the same name replaces the built-in one)."""
    specs = dict(_builtin())
    for d in reversed(model_dirs(model_dir)):  # earlier folders win
        if not d.is_dir():
            continue
        for p in sorted(d.glob("*.toml")):
            try:
                data = load_toml(p)
            except FormatError as e:
                log.warning("skipping %s: %s", p, e)
                continue
            if str(data.get("schema", "")).startswith(SPEC_SCHEMA + "/"):
                spec = ModelSpec.from_dict(data, str(p))
                specs[spec.name] = spec
    return specs


def get_spec(name: str | ModelSpec, model_dir: str | os.PathLike | None = None) -> ModelSpec:
    if isinstance(name, ModelSpec):
        return name
    if str(name).endswith(".toml") and Path(name).exists():
        return ModelSpec.load(name)
    specs = list_specs(model_dir)
    if name not in specs:
        raise UnknownNameError(
            f"unknown model {name!r}; known: {sorted(specs)}. Add a description "
            f"<name>.toml to a model folder ({', '.join(map(str, model_dirs(model_dir)))})."
        )
    return specs[name]


@cache  # read once: the configs ask for the presets on every construction (callers copy what they keep)
def _sets_toml() -> tuple[Path, dict[str, Any]]:
    path = Path(str(resources.files("roomcap.keypoints.models").joinpath("sets.toml")))
    data = load_toml(path)
    check_schema(data.get("schema"), SETS_SCHEMA, (1,), path)
    return path, data


def model_sets() -> dict[str, ModelSet]:
    path, data = _sets_toml()
    return {k: _strict(ModelSet, {"name": k, **v}, str(path)) for k, v in data["sets"].items()}


def presets() -> tuple[str, dict[str, dict[str, Any]]]:
    """The default preset's name and every preset's settings (``[presets]`` of ``sets.toml``; read by
    ``keypoints.presets.preset_config``)."""
    _, data = _sets_toml()
    table = dict(data.get("presets", {}))
    default = str(table.pop("default", ""))
    return default, {k: dict(v) for k, v in table.items()}


def get_model_set(name: str) -> ModelSet:
    """A named set, or ``"detector+pose"`` / ``"pose"`` built from model names."""
    sets = model_sets()
    if name in sets:
        return sets[name]
    if "+" in name:
        det, pose = name.split("+", 1)
        return ModelSet(name=name, detector=det, pose=pose)
    if name in list_specs():
        return ModelSet(name=name, pose=name)
    raise UnknownNameError(
        f"unknown model set {name!r}; known: {sorted(sets)} (or 'detector+pose' model names)."
    )


# ----------------------------------------------------------------------------- files and checksums


@cache
def _sha_cached(path: str, size: int, mtime_ns: int) -> str:
    return sha256_file(path)


def file_sha256(path: Path) -> str:
    st = path.stat()
    return _sha_cached(str(path), st.st_size, st.st_mtime_ns)


LOCK_NAME = "models.lock.toml"
LOCK_SCHEMA = "keypoint-model-lock"


def lock_file(folder: Path) -> Path:
    """The lock file of a model folder: the sha256 ``fetch`` saw for models whose description has none."""
    return Path(folder) / LOCK_NAME


def _read_lock(folder: Path) -> dict[str, dict[str, str]]:
    path = lock_file(folder)
    if not path.exists():
        return {}
    data = load_toml(path)
    check_schema(data.get("schema"), LOCK_SCHEMA, (1,), path)
    return {str(k): dict(v) for k, v in data.get("models", {}).items()}


def _record_lock(folder: Path, spec: ModelSpec, sha: str, url: str) -> Path:
    models = _read_lock(folder)
    models[spec.name] = {"file": spec.file, "sha256": sha, "url": url}
    path = lock_file(folder)
    save_toml(
        path,
        {"schema": f"{LOCK_SCHEMA}/1", "models": models},
        header="# sha256 of downloaded models whose descriptions have none (trust on first use); every\n"
        "# later load is checked against it. Delete an entry to accept a new download of that model.\n",
    )
    return path


def _recorded_sha(path: Path) -> str:
    """The digest ``fetch`` recorded for a model file: its folder's lock file, else an older ``.sha256``."""
    for entry in _read_lock(path.parent).values():
        if entry.get("file") == path.name:
            return str(entry.get("sha256", ""))
    side = path.with_name(path.name + ".sha256")
    return side.read_text().split()[0] if side.exists() else ""


def resolve(spec: str | ModelSpec, model_dir: str | os.PathLike | None = None, verify: bool = True) -> Path:
    """The model file on disk, checked against its sha256; ModelError saying where to get it otherwise."""
    spec = get_spec(spec, model_dir)
    dirs = model_dirs(model_dir)
    for d in dirs:
        p = d / spec.file
        if p.exists():
            if verify:
                expected = spec.sha256 or _recorded_sha(p)
                got = file_sha256(p)
                if expected and got != expected:
                    raise ModelError(
                        f"model '{spec.name}': {p} has sha256 {got}, the description ({spec.source}) expects "
                        f"{expected}. The file is damaged or another version. Delete it and "
                        + (
                            f"run `keypoints fetch {spec.name}`."
                            if spec.urls
                            else "copy the right file there."
                        )
                        + " A newer file needs its own description with its sha256."
                    )
                if not expected:
                    log.warning(
                        "model '%s': %s has no sha256 to check against (sha256 %s)", spec.name, p, got
                    )
            return p
    raise ModelError(
        f"model '{spec.name}': file {spec.file} not found in {[str(d) for d in dirs]}. " + spec.where_to_get()
    )


def fetch(
    spec: str | ModelSpec,
    model_dir: str | os.PathLike | None = None,
    force: bool = False,
    timeout_s: float = 60.0,
    progress: Progress | None = None,
) -> Path:
    """Download a model into the cache (or ``model_dir``), unpack OpenMMLab SDK zips, check the sha256.

    Tries ``url`` then each mirror. A description without a sha256 records the digest it saw beside the
    file (``<file>.sha256``) and later loads check against it. ``progress(done_bytes, total_bytes)`` is
    called while downloading.
    """
    spec = get_spec(spec, model_dir)
    dest_dir = Path(model_dir) if model_dir else cache_dir()
    dest = dest_dir / spec.file
    if not force:
        try:
            return resolve(spec, model_dir)
        except ModelError:
            pass
    if not spec.urls:
        raise ModelError(f"model '{spec.name}' has no download URL in {spec.source}. " + spec.where_to_get())
    dest_dir.mkdir(parents=True, exist_ok=True)
    errors = []
    for url in spec.urls:
        try:
            data = _download(url, timeout_s, progress)
        except OSError as e:
            errors.append(f"{url}: {e}")
            log.warning("download of %s failed: %s", url, e)
            continue
        payload = _unpack(data, spec, url)
        got = hashlib.sha256(payload).hexdigest()
        if spec.sha256 and got != spec.sha256:
            errors.append(f"{url}: sha256 {got} != expected {spec.sha256}")
            log.warning("download of %s has the wrong sha256 %s (expected %s)", url, got, spec.sha256)
            continue
        with atomic_path(dest) as tmp:
            tmp.write_bytes(payload)
        if not spec.sha256:
            lock = _record_lock(dest_dir, spec, got, url)
            log.warning(
                "model '%s' has no sha256 in its description: recorded the one of this download, %s, in %s "
                "(trust on first use); later loads are checked against it",
                spec.name,
                got,
                lock,
            )
        log.info("fetched %s -> %s (sha256 %s)", url, dest, got)
        return dest
    raise ModelError(
        f"model '{spec.name}': could not fetch a good copy of {spec.file}: {'; '.join(errors)}. "
        f"Download it by hand into {dest_dir} (or ROOMCAP_MODELS)."
    )


def _download(url: str, timeout_s: float, progress: Progress | None = None) -> bytes:
    with urllib.request.urlopen(url, timeout=timeout_s) as r, tempfile.TemporaryFile() as tmp:
        total = int(r.headers.get("Content-Length") or 0)
        done = 0
        while block := r.read(1 << 16):
            tmp.write(block)
            done += len(block)
            if progress:
                progress(url.rsplit("/", 1)[-1], done, total or None)
        if total and done != total:
            raise OSError(f"truncated download: {done} of {total} bytes")
        tmp.seek(0)
        return tmp.read()


def _unpack(data: bytes, spec: ModelSpec, url: str) -> bytes:
    """Bare ONNX passes through; a zip yields its ``archive_member`` (searched anywhere in the archive)."""
    if not data.startswith(b"PK\x03\x04"):
        return data
    member = spec.archive_member or spec.file
    with zipfile.ZipFile(io.BytesIO(data)) as z:
        names = [n for n in z.namelist() if n == member or n.endswith("/" + member)]
        if not names:
            raise ModelError(
                f"model '{spec.name}': archive {url} has no '{member}' (it holds {z.namelist()[:20]})."
            )
        with z.open(names[0]) as f:
            return f.read()
