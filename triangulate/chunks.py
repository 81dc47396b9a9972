"""Chunked files of the 3D stages: read an npz's arrays by rows, write outputs part by part (CONTRACTS.md).

Hours of 12 cameras x 16 people do not fit in memory as whole arrays, so the streaming stages read
their inputs in time chunks (:class:`NpzRows`: rows of one array of an ``.npz``, compressed or not,
decompressed as a stream, never the whole array) and write their outputs as a folder of parts with an
index (:class:`PartStore`), ``<file>.parts/``::

    triangulate/poses3d.parts/index.json     {"schema": "parts/1", "kind", "key", "chunks": [[f0, f1], ...],
                                              "parts": {"<i>": {"file", "size", "sha256"}}, "complete"}
    triangulate/poses3d.parts/part_00000.npz the ordinary file (poses3d/1, tracks/1) of frames [f0, f1)

A part is written atomically, then entered in the index with its size and sha256; a part that is
missing, of another size or another hash is rebuilt, never trusted. ``key`` hashes the inputs and the
settings: parts of another run (other detections, other config) are discarded. A killed run rerun with
the same inputs resumes at the first part that is not valid. The loaders (``Poses3D.load``,
``TrackFile.load``) read such a folder where the single file is absent.

The same layout is appendable (:meth:`PartStore.start_appending`, :meth:`PartStore.append`): the live
track of ``capture-run --live`` (``track/live.parts/``, read as ``track/live.npz``) does not know its
chunks in advance, so each part is written atomically and then entered, its chunk and its size and
sha256 together, in one atomic rewrite of the index (``"appendable": true``); ``complete`` is set when
the recording ends. A reader of such a folder sees only whole, listed parts, also while the recording
runs or after it was stopped (a warning says the parts are not complete); a part that does not match
the index is an error naming it, since a live part cannot be rebuilt.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
import zipfile
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from roomcap.core.errors import FormatError
from roomcap.core.fileio import atomic_write_text, sha256_file

PARTS_SCHEMA = "parts/1"

log = logging.getLogger(__name__)


def parts_dir(path: str | os.PathLike) -> Path:
    """The parts folder of a stage file: ``poses3d.npz`` -> ``poses3d.parts``."""
    p = Path(path)
    return p.with_suffix(".parts")


# The 3D stages' default ``chunk_s = "auto"``: a session of more than STREAM_ABOVE_FRAMES frames is
# streamed in chunks of STREAM_CHUNK_FRAMES frames (60 s at 25 Hz), a shorter one runs whole into the
# single file. Frames, not seconds: a stage's memory grows with the frames it holds (cameras x people per
# frame), whatever their rate. Measured in BENCHMARKS.md "Long sessions": the whole run of 1,500
# frames of 12 cameras x 16 people peaks as high as the streamed run of any length.
AUTO = "auto"
STREAM_ABOVE_FRAMES = 1500
STREAM_CHUNK_FRAMES = 1500


# Runs ``fn(*jobs[i])`` for every chunk ``i``, ``workers`` at a time, and yields ``(i, result)`` as each
# finishes; closing the generator stops the chunks not yet run (``pipeline.executors.chunk_runner``).
ChunkRunner = Callable[[Callable[..., Any], dict[int, tuple], int], Iterator[tuple[int, Any]]]

CHUNK_EXECUTORS = ("processes", "ray")  # where StreamConfig.executor runs the chunks of one session
STREAM_KEYS = ("chunk_s", "workers", "executor")


@dataclass(frozen=True)
class StreamConfig:
    """How a 3D stage walks a session in time chunks; the one place these settings are parsed.

    chunk_s: stream the session in chunks of this many seconds: the inputs are read chunk by chunk and
      the output is written as a parts folder (``<file>.parts/``, :class:`PartStore`), so memory does not
      grow with the session and a killed run resumes at the last complete chunk; 0 = the whole session
      at once into the single file; ``"auto"`` (the default) = streamed in chunks of
      ``STREAM_CHUNK_FRAMES`` frames when the session has more than ``STREAM_ABOVE_FRAMES``
      (:meth:`seconds`). The parts hold the same results as the single file.
    workers: how many processes run independent chunks at once (the triangulation's frames are
      independent; a tracker carries its state from chunk to chunk and runs them in order).
    executor: where those chunks run: ``processes`` (spawned processes of this machine) or ``ray`` (one
      Ray task of one CPU per chunk; ``reprocess --executor ray`` sets it for the sessions it streams).
    ``workers`` and ``executor`` say how the chunks ran, not what they hold (:meth:`result_settings`).

    >>> StreamConfig(chunk_s=30).seconds(n_frames=100, fps=25.0)
    30.0
    >>> StreamConfig().seconds(n_frames=9000, fps=25.0), StreamConfig().seconds(n_frames=100, fps=25.0)
    (60.0, 0.0)
    >>> StreamConfig(chunk_s=-1)  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ValueError: chunk_s must be "auto" (stream sessions longer than 1500 frames) or seconds >= 0 ...
    """

    chunk_s: float | str = AUTO
    workers: int = 1
    executor: str = "processes"

    def __post_init__(self) -> None:
        object.__setattr__(self, "chunk_s", _parse_chunk_s(self.chunk_s))
        if isinstance(self.workers, bool) or not isinstance(self.workers, int) or self.workers < 1:
            raise ValueError(f"workers must be an integer >= 1, got {self.workers!r}.")
        if self.executor not in CHUNK_EXECUTORS:
            raise ValueError(f"executor must be one of {list(CHUNK_EXECUTORS)}, got {self.executor!r}.")

    @property
    def streams(self) -> bool:
        """False when the stage runs whole whatever the session's length (``chunk_s = 0``)."""
        return self.chunk_s != 0

    def seconds(self, n_frames: int, fps: float) -> float:
        """Seconds per chunk for a session of ``n_frames`` at ``fps`` (0 = whole)."""
        if self.chunk_s != AUTO:
            return float(self.chunk_s)
        return STREAM_CHUNK_FRAMES / fps if n_frames > STREAM_ABOVE_FRAMES and fps > 0 else 0.0

    def check_in_order(self) -> None:
        """For a stage whose chunks depend on the one before (a tracker): one process, in order."""
        if self.workers != 1 or self.executor != "processes":
            raise ValueError(
                "workers and executor: a tracker carries its tracks from one chunk to the next, so its "
                "chunks run in order in one process; set them on [triangulate.options] only."
            )

    def result_settings(self) -> dict[str, Any]:
        """What the parts depend on (``chunk_s``), without how they were run (``workers``, ``executor``)."""
        return {"chunk_s": self.chunk_s}


def split_stream_keys(data: Mapping[str, Any]) -> tuple[dict[str, Any], dict[str, Any]]:
    """A stage's flat options (``[track.options] chunk_s = 30``) split into its own and its ``stream``'s.

    >>> split_stream_keys({"chunk_s": 30, "min_joints_3d": 4})
    ({'min_joints_3d': 4}, {'chunk_s': 30})
    """
    own = {k: v for k, v in data.items() if k not in STREAM_KEYS}
    stream = {k: v for k, v in data.items() if k in STREAM_KEYS}
    if "stream" in own:
        stream = {**dict(own.pop("stream")), **stream}
    return own, stream


def _parse_chunk_s(value: object) -> float | str:
    """``"auto"`` or seconds >= 0 (0 = the whole session at once)."""
    if value == AUTO:
        return AUTO
    try:
        seconds = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        seconds = float("nan")
    if isinstance(value, bool) or not seconds >= 0:
        raise ValueError(
            f'chunk_s must be "auto" (stream sessions longer than {STREAM_ABOVE_FRAMES} frames) or '
            f"seconds >= 0 (0 = the whole session at once), got {value!r}."
        )
    return seconds


def hash_key(items: Iterable[object]) -> str:
    """A short hash of the inputs and settings of a run (what makes its parts reusable)."""
    h = hashlib.sha256()
    for it in items:
        h.update(repr(it).encode())
        h.update(b"\0")
    return h.hexdigest()[:32]


def file_stamp(path: Path) -> tuple[str, int, int]:
    """(name, size, mtime_ns) of an input file: cheap identity for the run key."""
    st = path.stat()
    return (path.name, st.st_size, st.st_mtime_ns)


class PartStore:
    """The parts folder of one output (see the module docstring)."""

    def __init__(self, folder: str | os.PathLike, kind: str) -> None:
        self.folder = Path(folder)
        self.kind = kind
        self.index_path = self.folder / "index.json"
        self.index: dict = {}

    # -- writing
    def open(self, key: str, chunks: list[tuple[int, int]], meta: dict | None = None) -> list[int]:
        """Start or resume a run: returns the chunk numbers whose parts must be (re)built."""
        old = self._read_index(strict=False)
        chunks = [[int(a), int(b)] for a, b in chunks]
        if old and old.get("key") == key and old.get("chunks") == chunks and old.get("kind") == self.kind:
            self.index = old
        else:
            if self.folder.exists():
                shutil.rmtree(self.folder)
            self.index = {
                "schema": PARTS_SCHEMA,
                "kind": self.kind,
                "key": key,
                "chunks": chunks,
                "parts": {},
                "meta": meta or {},
                "complete": False,
            }
        self.folder.mkdir(parents=True, exist_ok=True)
        self.index["complete"] = False
        todo = [i for i in range(len(chunks)) if not self.valid(i)]
        for i in todo:
            self.index["parts"].pop(str(i), None)
        self._write_index()
        return todo

    def part_path(self, i: int) -> Path:
        return self.folder / f"part_{i:05d}.npz"

    def commit(self, i: int) -> None:
        """Enter part ``i`` (already written atomically at :meth:`part_path`) in the index."""
        p = self.part_path(i)
        self.index["parts"][str(i)] = {"file": p.name, "size": p.stat().st_size, "sha256": sha256_file(p)}
        self._write_index()

    # -- appending (chunks not known in advance: the live track)
    def start_appending(self, key: str, meta: dict | None = None) -> None:
        """Start an appendable store: an earlier folder (a previous recording's parts) is removed and an
        index with no parts is written."""
        if self.folder.exists():
            shutil.rmtree(self.folder)
        self.folder.mkdir(parents=True)
        self.index = {
            "schema": PARTS_SCHEMA,
            "kind": self.kind,
            "key": key,
            "chunks": [],
            "parts": {},
            "meta": meta or {},
            "appendable": True,
            "complete": False,
        }
        self._write_index()

    @property
    def next_part_path(self) -> Path:
        """Where the part that :meth:`append` enters next is written (atomically, by the caller)."""
        return self.part_path(len(self.index["chunks"]))

    def append(self, n_rows: int, meta: dict | None = None) -> int:
        """Enter the part written at :attr:`next_part_path`, of ``n_rows`` rows following the last chunk:
        its chunk and its size and sha256 (and ``meta``'s keys, updated) in one atomic rewrite of the index.
        Returns its number."""
        if not self.index.get("appendable"):
            raise RuntimeError(f"{self.folder} was not started with start_appending()")
        chunks = self.index["chunks"]
        i, p = len(chunks), self.next_part_path
        a = chunks[-1][1] if chunks else 0
        chunks.append([a, a + int(n_rows)])
        if meta:
            self.index.setdefault("meta", {}).update(meta)
        self.index["parts"][str(i)] = {"file": p.name, "size": p.stat().st_size, "sha256": sha256_file(p)}
        self.index["complete"] = False
        self._write_index()
        return i

    def finish(self, meta: dict | None = None) -> None:
        if meta:
            self.index.setdefault("meta", {}).update(meta)
        missing = [i for i in range(len(self.index["chunks"])) if str(i) not in self.index["parts"]]
        if missing:
            raise RuntimeError(f"parts {missing} of {self.folder} were not written")
        self.index["complete"] = True
        self._write_index()

    def valid(self, i: int) -> bool:
        e = self.index.get("parts", {}).get(str(i))
        if not e:
            return False
        p = self.folder / e["file"]
        try:
            return p.stat().st_size == e["size"] and sha256_file(p) == e["sha256"]
        except OSError:
            return False

    def _write_index(self) -> None:
        # compact: json's C encoder (indent falls back to the Python one, 4x slower); the index is
        # rewritten after every part, and an hour's live track has thousands of them
        atomic_write_text(self.index_path, json.dumps(self.index, separators=(",", ":")))

    # -- reading
    def _read_index(self, strict: bool = True) -> dict:
        try:
            d = json.loads(self.index_path.read_text())
            if d.get("schema") != PARTS_SCHEMA or "chunks" not in d or "parts" not in d:
                raise ValueError("not a parts/1 index")
            return d
        except (OSError, ValueError) as e:
            if not strict:
                return {}
            raise FormatError(
                self.index_path,
                None,
                f"cannot read the parts index ({e}).",
                "Delete the folder and rerun the stage that writes it.",
            ) from None

    def load_index(self) -> dict:
        """The index of a finished run; a run that did not finish or a damaged part is an error. An
        appendable store (the live track) is read as far as it was written, with a warning when it
        is not complete (the recording is running, or was stopped)."""
        self.index = self._read_index()
        if not self.index.get("complete") and self.index.get("appendable"):
            log.warning(
                "%s: the %s parts are not complete (the recording is still running or was stopped); "
                "reading the %d parts written",
                self.folder,
                self.kind,
                len(self.index["chunks"]),
            )
        elif not self.index.get("complete"):
            raise FormatError(
                self.index_path,
                "complete",
                f"the {self.kind} parts are incomplete (the run was stopped).",
                "Rerun the stage: it resumes from the last complete part.",
            )
        return self.index

    def checked_parts(self) -> list[tuple[int, int, Path]]:
        """(f0, f1, path) of every part, each checked against its size and hash in the index."""
        idx = self.load_index()
        if not idx["chunks"]:
            raise FormatError(
                self.index_path, "chunks", f"no {self.kind} parts written yet.", "Read it again later."
            )
        out = []
        for i, (a, b) in enumerate(idx["chunks"]):
            e = idx["parts"].get(str(i))
            path = self.folder / e["file"] if e else self.part_path(i)
            if not self.valid(i):
                raise FormatError(
                    path,
                    None,
                    f"part {i} is missing or does not match its size and sha256 in index.json "
                    "(truncated or changed); it is not read.",
                    "A live recording's parts cannot be rebuilt: reprocess the session "
                    "(reprocess SESSION) for a track made from its videos."
                    if idx.get("appendable")
                    else "Rerun the stage: it rebuilds the damaged parts.",
                )
            out.append((a, b, path))
        return out


def remove_output(path: str | os.PathLike) -> None:
    """Remove a stage output in either layout (the single file and its parts folder)."""
    p = Path(path)
    if p.exists():
        p.unlink()
    if parts_dir(p).exists():
        shutil.rmtree(parts_dir(p))


class NpzRows:
    """Rows ``[a, b)`` of the arrays of one ``.npz`` along their first axis, read as a stream.

    Members stored or deflated are both read without loading a whole array: a read at or after the
    last position continues the stream; a read before it reopens the member. Small arrays
    (:meth:`full`) are read whole."""

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)
        try:
            self._zf = zipfile.ZipFile(self.path)
            self.names = {n[:-4] for n in self._zf.namelist() if n.endswith(".npy")}
        except (OSError, zipfile.BadZipFile) as e:
            raise FormatError(
                self.path, None, f"cannot be read as npz ({e}); the file is truncated or corrupt.", ""
            ) from None
        self._streams: dict[str, tuple] = {}

    def close(self) -> None:
        for s in self._streams.values():
            s[0].close()
        self._streams.clear()
        self._zf.close()

    def __enter__(self) -> NpzRows:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def full(self, name: str) -> np.ndarray:
        try:
            with self._zf.open(name + ".npy") as f:
                return np.lib.format.read_array(f, allow_pickle=False)
        except (KeyError, OSError, ValueError, EOFError, zipfile.BadZipFile) as e:
            raise FormatError(self.path, name, f"cannot read the array ({e}).", "") from None

    def header(self, name: str) -> tuple[tuple[int, ...], np.dtype]:
        with self._zf.open(name + ".npy") as f:
            shape, fortran, dtype = self._read_header(f)
        return shape, dtype

    def _read_header(self, f) -> tuple[tuple[int, ...], bool, np.dtype]:
        version = np.lib.format.read_magic(f)
        if version == (1, 0):
            shape, fortran, dtype = np.lib.format.read_array_header_1_0(f)
        else:
            shape, fortran, dtype = np.lib.format.read_array_header_2_0(f)
        return shape, fortran, dtype

    def rows(self, name: str, a: int, b: int) -> np.ndarray:
        """(b - a, ...) rows of array ``name``."""
        s = self._streams.get(name)
        if s is None or s[4] > a:
            if s is not None:
                s[0].close()
            f = self._zf.open(name + ".npy")
            shape, fortran, dtype = self._read_header(f)
            if fortran and len(shape) > 1:
                f.close()
                return self.full(name)[a:b]
            row = int(np.prod(shape[1:], dtype=np.int64)) * dtype.itemsize
            s = (f, shape, dtype, row, 0)
        f, shape, dtype, row, pos = s
        a, b = max(a, 0), min(b, shape[0])
        try:
            skip = (a - pos) * row
            while skip > 0:
                got = len(f.read(min(skip, 1 << 24)))
                if got == 0:
                    raise EOFError("the array ends early")
                skip -= got
            n = max(b - a, 0)
            buf = f.read(n * row)
            if len(buf) != n * row:
                raise EOFError("the array ends early")
        except (OSError, EOFError, zipfile.BadZipFile) as e:
            raise FormatError(
                self.path, name, f"cannot read rows {a}-{b} ({e}); the file is truncated or corrupt.", ""
            ) from None
        self._streams[name] = (f, shape, dtype, row, max(b, a))
        return np.frombuffer(buf, dtype=dtype).reshape((n, *shape[1:])).copy()
