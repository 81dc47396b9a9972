"""Atomic writes, schema tags and safe loads shared by every stage's files.

Every file the project writes carries ``schema`` = ``"<name>/<version>"``;
readers reject other names and unknown versions with a message that names
the file and says what to do. Writes go to a temporary file in the same
folder followed by ``os.replace``, so a reader never sees half a file and a
killed writer leaves the previous version intact.
"""

from __future__ import annotations

import hashlib
import io
import os
import tempfile
import tomllib
import zipfile
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from roomcap.core.errors import FormatError, SchemaError

T = TypeVar("T")


# ----------------------------------------------------------------------------- atomic writes

_UMASK = os.umask(0)
os.umask(_UMASK)


@contextmanager
def atomic_path(path: str | os.PathLike[str], suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success it is renamed over ``path``.

    ``suffix`` defaults to the target's suffix, so libraries that pick a format
    by extension (numpy, OpenCV, matplotlib) write the right thing.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(
        prefix=f".{path.name}.", suffix=suffix if suffix is not None else path.suffix, dir=path.parent
    )
    os.close(fd)
    os.chmod(tmp, 0o666 & ~_UMASK)  # mkstemp makes 0600; outputs get the usual permissions
    try:
        yield Path(tmp)
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise


def atomic_write_bytes(path: str | os.PathLike[str], data: bytes) -> None:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def atomic_write_text(path: str | os.PathLike[str], text: str) -> None:
    """Write ``text`` as UTF-8 through :func:`atomic_path`: readers see the old or the new file, never a part.

    >>> import tempfile
    >>> folder = Path(tempfile.mkdtemp())
    >>> atomic_write_text(folder / "sub" / "note.txt", "done")
    >>> (folder / "sub" / "note.txt").read_text(), sorted(p.name for p in (folder / "sub").iterdir())
    ('done', ['note.txt'])
    """
    atomic_write_bytes(path, text.encode("utf-8"))


def sha256_file(path: str | os.PathLike[str]) -> str:
    """sha256 of a whole file, read in 1 MiB blocks (about 1.2 GB/s on one core with SHA instructions).

    >>> import tempfile
    >>> path = Path(tempfile.mkdtemp()) / "a.bin"
    >>> _ = path.write_bytes(b"abc")
    >>> sha256_file(path)[:16]
    'ba7816bf8f01cfea'
    """
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(1 << 20):
            h.update(block)
    return h.hexdigest()


# ----------------------------------------------------------------------------- schema tags


def schema_tag(name: str, version: int) -> str:
    """The ``schema`` value every file carries.

    >>> schema_tag("tracks", 2)
    'tracks/2'
    """
    return f"{name}/{version}"


def check_schema(tag: Any, name: str, supported: tuple[int, ...], path: str | os.PathLike[str] | None) -> int:
    """Parse ``"name/version"`` and return the version; raise SchemaError otherwise.

    >>> check_schema("tracks/2", "tracks", (1, 2), "t.npz")
    2
    >>> check_schema("tracks/3", "tracks", (1, 2), "t.npz")  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    roomcap.core.errors.SchemaError: t.npz: field 'schema': version 3 is not supported (...). Upgrade ...
    >>> check_schema("detections/1", "tracks", (1,), "t.npz")  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    roomcap.core.errors.SchemaError: t.npz: field 'schema': this is a 'detections' file, expected ...
    """
    if isinstance(tag, np.ndarray):
        tag = tag.item() if tag.shape == () else None
    if not isinstance(tag, str) or "/" not in tag:
        raise SchemaError(
            path,
            "schema",
            f"missing or malformed schema tag {tag!r}; expected '{name}/<version>'.",
            "Write the file with this project's writer or add the schema key.",
        )
    got_name, _, got_version = tag.rpartition("/")
    if got_name != name:
        raise SchemaError(
            path,
            "schema",
            f"this is a '{got_name}' file, expected '{name}'.",
            "Check that the path points at the right file.",
        )
    try:
        version = int(got_version)
    except ValueError:
        raise SchemaError(path, "schema", f"version {got_version!r} is not an integer.") from None
    if version not in supported:
        newer = version > max(supported)
        raise SchemaError(
            path,
            "schema",
            f"version {version} is not supported (this code reads {name} versions {list(supported)}).",
            "Upgrade roomcap to read files written by a newer version."
            if newer
            else "Re-create the file with this version of roomcap.",
        )
    return version


# ----------------------------------------------------------------------------- npz


def save_npz(path: str | os.PathLike[str], arrays: Mapping[str, Any], compress: bool = True) -> None:
    """Write an npz atomically. Strings become 0-d or 1-d unicode arrays, never object arrays.

    The bytes depend on the arrays only (fixed member time stamps), so a rerun writes the same file:

    >>> import tempfile
    >>> folder = Path(tempfile.mkdtemp())
    >>> save_npz(folder / "a.npz", {"schema": "demo/1", "xyz_m": np.zeros((2, 3))})
    >>> save_npz(folder / "b.npz", {"schema": "demo/1", "xyz_m": np.zeros((2, 3))})
    >>> (folder / "a.npz").read_bytes() == (folder / "b.npz").read_bytes()
    True
    >>> save_npz(folder / "c.npz", {"bad": np.array([{}], dtype=object)})  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    TypeError: save_npz(...): 'bad' is an object array; store strings or numbers only
    """
    clean: dict[str, np.ndarray] = {}
    for key, value in arrays.items():
        arr = np.asarray(value)
        if arr.dtype == object:
            raise TypeError(f"save_npz({path}): '{key}' is an object array; store strings or numbers only")
        clean[key] = arr
    # Written by hand rather than np.savez: numpy stamps each member with the current
    # time, and byte-identical reruns (pipeline caching, resume tests) need fixed stamps.
    buf = io.BytesIO()
    method = zipfile.ZIP_DEFLATED if compress else zipfile.ZIP_STORED
    with zipfile.ZipFile(buf, "w", compression=method, allowZip64=True) as zf:
        for key, arr in clean.items():
            info = zipfile.ZipInfo(f"{key}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = method
            info.external_attr = 0o644 << 16
            with zf.open(info, "w", force_zip64=True) as f:
                np.lib.format.write_array(f, arr, allow_pickle=False)
    atomic_write_bytes(path, buf.getvalue())


def load_npz(path: str | os.PathLike[str], required: tuple[str, ...] = ()) -> dict[str, np.ndarray]:
    """Load every array of an npz with ``allow_pickle=False``; a truncated file gets a FormatError.

    >>> import tempfile
    >>> path = Path(tempfile.mkdtemp()) / "poses.npz"
    >>> save_npz(path, {"schema": "demo/1", "fps": 25.0})
    >>> data = load_npz(path, required=("schema", "fps"))
    >>> npz_str(data, "schema"), float(data["fps"])
    ('demo/1', 25.0)
    >>> _ = path.write_bytes(b"not a zip")
    >>> load_npz(path)  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    roomcap.core.errors.FormatError: ...poses.npz: is not an npz archive (numpy's zip of arrays); it may ...
    """
    path = Path(path)
    if not path.exists():
        raise FormatError(path, None, "file does not exist.")
    with open(path, "rb") as f:
        magic = f.read(4)
    if magic != b"PK\x03\x04" and magic != b"PK\x05\x06":  # an npz is a zip archive (empty: end record only)
        what = "is empty" if not magic else "is not an npz archive (numpy's zip of arrays)"
        raise FormatError(
            path,
            None,
            f"{what}; it may be another kind of file given the .npz name, or a write that never finished.",
            "Give the file the stage wrote, or delete it and rerun the stage that writes it.",
        )
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except (zipfile.BadZipFile, EOFError, OSError, ValueError) as e:
        raise FormatError(
            path,
            None,
            f"cannot be read as npz ({e}); the file is truncated or corrupt.",
            "Delete it and rerun the stage that writes it.",
        ) from e
    require_keys(path, data, required)
    return data


def require_keys(
    path: str | os.PathLike[str], data: Mapping[str, np.ndarray], required: tuple[str, ...]
) -> None:
    """FormatError naming the first of ``required`` that ``data`` (an npz read by ``load_npz``) lacks.

    >>> require_keys("t.npz", {"fps": np.float64(25)}, ("fps", "xyz_m"))  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    roomcap.core.errors.FormatError: t.npz: field 'xyz_m': required keys ['xyz_m'] are missing (present: ...
    """
    missing = [k for k in required if k not in data]
    if missing:
        raise FormatError(
            Path(path),
            missing[0],
            f"required keys {missing} are missing (present: {sorted(data)}).",
            "The file was written by another tool or is incomplete; rerun the stage that writes it.",
        )


def load_container(
    path: str | os.PathLike[str], schema: str, versions: tuple[int, ...], required: tuple[str, ...]
) -> dict[str, np.ndarray]:
    """The arrays of one of the project's files (detections, poses3d, tracks): read, its schema tag
    checked, its required keys present; the load checks every data container shares.

    >>> import tempfile
    >>> path = Path(tempfile.mkdtemp()) / "tracks.npz"
    >>> save_npz(path, {"schema": "tracks/1", "fps": 25.0})
    >>> float(load_container(path, "tracks", (1,), ("fps",))["fps"])
    25.0
    >>> load_container(path, "tracks", (1,), ("fps", "xyz_m"))  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    roomcap.core.errors.FormatError: ...tracks.npz: field 'xyz_m': required keys ['xyz_m'] are missing ...
    """
    data = load_npz(path, required=("schema",))
    check_schema(data["schema"], schema, versions, path)
    require_keys(path, data, required)  # after the schema check, on the arrays already read
    return data


@contextmanager
def errors_in(path: str | os.PathLike[str]) -> Iterator[None]:
    """A container's own checks (shapes, values) raised while it is built from ``path`` name the file.

    >>> with errors_in("t.npz"):  # doctest: +ELLIPSIS
    ...     raise FormatError(None, "fps", "must be a positive number, got 0.")
    Traceback (most recent call last):
    roomcap.core.errors.FormatError: t.npz: field 'fps': must be a positive number, got 0.
    """
    try:
        yield
    except FormatError as e:
        raise FormatError(Path(path), e.field, str(e).split(": ", 2)[-1]) from e


def npz_str(data: Mapping[str, np.ndarray], key: str) -> str:
    """A string stored as a 0-d array, as Python text.

    >>> npz_str({"skeleton": np.array("body19")}, "skeleton")
    'body19'
    """
    return str(np.asarray(data[key]).item())


# ----------------------------------------------------------------------------- toml


def load_toml(path: str | os.PathLike[str]) -> dict[str, Any]:
    """A TOML file as a dict; a missing or malformed file is a FormatError naming it.

    >>> import tempfile
    >>> path = Path(tempfile.mkdtemp()) / "run.toml"
    >>> save_toml(path, {"track": {"tracker": "particle", "fps": np.float64(25.0)}}, header="a test")
    >>> load_toml(path)
    {'track': {'tracker': 'particle', 'fps': 25.0}}
    >>> _ = path.write_text("[track")
    >>> load_toml(path)  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    roomcap.core.errors.FormatError: ...run.toml: is not valid TOML (...).
    """
    path = Path(path)
    if not path.exists():
        raise FormatError(path, None, "file does not exist.")
    try:
        with open(path, "rb") as f:
            return tomllib.load(f)
    except tomllib.TOMLDecodeError as e:
        raise FormatError(path, None, f"is not valid TOML ({e}).") from e


def save_toml(path: str | os.PathLike[str], data: Mapping[str, Any], header: str = "") -> None:
    import tomli_w

    text = tomli_w.dumps(_toml_ready(data))
    if header:
        text = "".join(f"# {line}\n" if line else "#\n" for line in header.splitlines()) + "\n" + text
    atomic_write_text(path, text)


def _toml_ready(value: Any) -> Any:
    """Numpy scalars/arrays to plain Python so tomli_w writes every digit."""
    if isinstance(value, Mapping):
        return {str(k): _toml_ready(v) for k, v in value.items() if v is not None}
    if isinstance(value, np.ndarray):
        return _toml_ready(value.tolist())
    if isinstance(value, (list, tuple)):
        return [_toml_ready(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    return value
