"""Calibration boards: ChArUco, checkerboard and ArUco grid, described in a small TOML file.

This project's board file (``schema = "board/1"``)::

    schema = "board/1"
    kind = "charuco"            # "charuco" | "checkerboard" | "aruco_grid"
    squares = [5, 7]            # charuco: squares across, down
    square_size_m = 0.04
    marker_size_m = 0.03        # charuco and aruco_grid
    dictionary = "DICT_4X4_50"  # any cv2.aruco.DICT_* name
    legacy_pattern = false      # charuco boards printed with OpenCV < 4.6 and an even number of rows
    inverted = false            # white markers on black (caliscope's "inverted")

    # checkerboard:  inner_corners = [9, 6], square_size_m = 0.025
    # aruco_grid:    markers = [4, 5], marker_size_m = 0.04, marker_separation_m = 0.01

caliscope's ``charuco.toml`` (columns, rows, dictionary, aruco_scale, square_size_override_cm,
inverted, units, board_width/height) is read as well, so its users keep their files.

Board frame: x along the columns, y along the rows (down the printed image), z = x cross y,
i.e. into the board when looking at its printed side; metres.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from roomcap.core.config import check_keys
from roomcap.core.errors import FormatError, InputError, RoomcapError
from roomcap.core.fileio import check_schema, load_toml, save_toml, schema_tag

__all__ = ["Board", "CalibrationError", "load_board", "save_board", "DICTIONARIES", "BOARD_KINDS"]


class CalibrationError(RoomcapError, RuntimeError):
    """Calibration cannot go on: the message says what happened and what to do."""


BOARD_SCHEMA = "board"
BOARD_VERSION = 1
BOARD_KINDS = ("charuco", "checkerboard", "aruco_grid")
_KEYS = (
    "schema",
    "kind",
    "squares",
    "inner_corners",
    "markers",
    "square_size_m",
    "marker_size_m",
    "marker_separation_m",
    "dictionary",
    "legacy_pattern",
    "inverted",
    "name",
)


def _dictionaries() -> tuple[str, ...]:
    import cv2

    return tuple(sorted(n for n in dir(cv2.aruco) if n.startswith("DICT_")))


DICTIONARIES = _dictionaries()


@dataclass(frozen=True)
class Board:
    """A calibration board. ``grid``: (columns, rows) of squares (charuco), inner corners
    (checkerboard) or markers (aruco_grid). Sizes in metres."""

    kind: str
    grid: tuple[int, int]
    square_size_m: float
    marker_size_m: float = 0.0
    dictionary: str = "DICT_4X4_50"
    legacy_pattern: bool = False
    inverted: bool = False
    marker_separation_m: float = 0.0
    name: str = ""
    _cache: dict = field(default_factory=dict, repr=False, compare=False, hash=False)

    def __post_init__(self) -> None:
        if self.kind not in BOARD_KINDS:
            raise InputError(f"board kind {self.kind!r} is not one of {list(BOARD_KINDS)}")
        g = tuple(int(v) for v in self.grid)
        if len(g) != 2 or min(g) < 2:
            raise InputError(f"board grid must be two integers >= 2, got {self.grid!r}")
        object.__setattr__(self, "grid", g)
        for k in ("square_size_m", "marker_size_m", "marker_separation_m"):
            v = getattr(self, k)
            if isinstance(v, (str, bytes)) or not np.isfinite(float(v)):
                raise InputError(f"board {k} must be a number (metres), got {v!r}")
            object.__setattr__(self, k, float(v))
        if not isinstance(self.dictionary, str):
            raise InputError(
                f"board dictionary must be a name such as 'DICT_4X4_50', got {self.dictionary!r}"
            )
        if self.kind == "charuco" and min(g) < 3:
            raise InputError(f"a ChArUco board needs at least 3x3 squares, got {g}")
        if self.kind in ("charuco", "checkerboard") and not self.square_size_m > 0:
            raise InputError(f"square_size_m must be > 0, got {self.square_size_m}")
        if self.kind in ("charuco", "aruco_grid"):
            if not self.marker_size_m > 0:
                raise InputError(
                    f"marker_size_m must be > 0 for a {self.kind} board, got {self.marker_size_m}"
                )
            if self.kind == "charuco" and self.marker_size_m >= self.square_size_m:
                raise InputError(
                    f"marker_size_m ({self.marker_size_m}) must be smaller than square_size_m "
                    f"({self.square_size_m})"
                )
            if self.dictionary not in DICTIONARIES:
                raise InputError(f"unknown dictionary {self.dictionary!r}; valid: {', '.join(DICTIONARIES)}")

    # ---- geometry

    @property
    def uses_markers(self) -> bool:
        return self.kind in ("charuco", "aruco_grid")

    @property
    def n_points(self) -> int:
        return len(self.object_points())

    def object_points(self) -> np.ndarray:
        """Board points (N,3) in metres in the board frame; point id = row index."""
        if "obj" not in self._cache:
            if self.kind == "charuco":
                obj = np.asarray(self.cv_board().getChessboardCorners(), np.float64).reshape(-1, 3)
            elif self.kind == "checkerboard":
                cx, cy = self.grid
                xs, ys = np.meshgrid(np.arange(cx), np.arange(cy))
                obj = np.stack([xs.ravel(), ys.ravel(), np.zeros(cx * cy)], 1) * self.square_size_m
            else:
                obj = np.concatenate(
                    [np.asarray(o, np.float64).reshape(4, 3) for o in self.cv_board().getObjPoints()]
                )
            obj.setflags(write=False)
            self._cache["obj"] = obj
        return self._cache["obj"]

    def extent_m(self) -> tuple[float, float]:
        """Printed size (width, height) in metres."""
        if self.kind == "charuco":
            return self.grid[0] * self.square_size_m, self.grid[1] * self.square_size_m
        if self.kind == "checkerboard":
            return (self.grid[0] + 1) * self.square_size_m, (self.grid[1] + 1) * self.square_size_m
        w = self.grid[0] * self.marker_size_m + (self.grid[0] - 1) * self.marker_separation_m
        h = self.grid[1] * self.marker_size_m + (self.grid[1] - 1) * self.marker_separation_m
        return w, h

    def cv_dictionary(self):
        import cv2

        return cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))

    def cv_board(self):
        """The OpenCV board object (CharucoBoard or GridBoard); None for a checkerboard."""
        import cv2

        if self.kind == "charuco":
            b = cv2.aruco.CharucoBoard(
                self.grid, self.square_size_m, self.marker_size_m, self.cv_dictionary()
            )
            b.setLegacyPattern(bool(self.legacy_pattern))
            return b
        if self.kind == "aruco_grid":
            return cv2.aruco.GridBoard(
                self.grid, self.marker_size_m, self.marker_separation_m, self.cv_dictionary()
            )
        return None

    def render(self, px_per_m: float = 4000.0, margin_px: int = 0) -> np.ndarray:
        """The printed board as a grayscale image (H,W) uint8; board point (x,y) in metres maps to pixel
        (x * px_per_m + margin_px, y * px_per_m + margin_px) (pixel centres).
        Inverted boards render inverted."""
        import cv2

        w_m, h_m = self.extent_m()
        W, H = round(w_m * px_per_m), round(h_m * px_per_m)
        if self.kind == "checkerboard":
            s = self.square_size_m * px_per_m
            yy, xx = np.mgrid[0:H, 0:W]
            img = (((np.floor((xx + 0.5) / s) + np.floor((yy + 0.5) / s)) % 2) * 255).astype(np.uint8)
            img = 255 - img  # top-left square black
        else:
            img = self.cv_board().generateImage((W, H), marginSize=0, borderBits=1)
        if self.inverted:
            img = 255 - img
        if margin_px:
            img = cv2.copyMakeBorder(
                img,
                margin_px,
                margin_px,
                margin_px,
                margin_px,
                cv2.BORDER_CONSTANT,
                value=0 if self.inverted else 255,
            )
        return img

    def image_origin_m(self) -> float:
        """Board coordinate (x = y) of the top-left edge of ``render()`` (checkerboard: one square before
        the first inner corner; others: 0)."""
        return -self.square_size_m if self.kind == "checkerboard" else 0.0

    # ---- identity

    def detection_key(self) -> str:
        """Hash of what changes detected pixels and ids (not the physical sizes): used to key the cache."""
        # dictionaries of one family (DICT_5X5_50/100/250/1000) share their first markers, and a board uses
        # markers 0..n-1: detections do not depend on which one of the family is named
        fam = self.dictionary.rsplit("_", 1)
        dict_key = fam[0] if len(fam) == 2 and fam[1].isdigit() else self.dictionary
        d = {
            "kind": self.kind,
            "grid": list(self.grid),
            "dictionary": dict_key if self.uses_markers else "",
            "legacy": bool(self.legacy_pattern) and self.kind == "charuco",
            "inverted": bool(self.inverted),
        }
        if self.kind == "charuco":
            d["ratio"] = round(self.marker_size_m / self.square_size_m, 6)
        return hashlib.sha256(json.dumps(d, sort_keys=True).encode()).hexdigest()[:16]

    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {"schema": schema_tag(BOARD_SCHEMA, BOARD_VERSION), "kind": self.kind}
        if self.name:
            d["name"] = self.name
        key = {"charuco": "squares", "checkerboard": "inner_corners", "aruco_grid": "markers"}[self.kind]
        d[key] = list(self.grid)
        if self.square_size_m > 0:
            d["square_size_m"] = self.square_size_m
        if self.uses_markers:
            d["marker_size_m"] = self.marker_size_m
            d["dictionary"] = self.dictionary
        if self.kind == "aruco_grid":
            d["marker_separation_m"] = self.marker_separation_m
        if self.kind == "charuco":
            d["legacy_pattern"] = bool(self.legacy_pattern)
        d["inverted"] = bool(self.inverted)
        return d

    def describe(self) -> str:
        g = f"{self.grid[0]}x{self.grid[1]}"
        if self.kind == "charuco":
            return (
                f"ChArUco {g} squares of {self.square_size_m * 100:g} cm, markers "
                f"{self.marker_size_m * 100:g} cm, "
                f"{self.dictionary}, legacy_pattern={self.legacy_pattern}, inverted={self.inverted}"
            )
        if self.kind == "checkerboard":
            return (
                f"checkerboard {g} inner corners of {self.square_size_m * 100:g} cm, inverted={self.inverted}"
            )
        return f"ArUco grid {g} markers of {self.marker_size_m * 100:g} cm, {self.dictionary}"

    def replace(self, **kw: Any) -> Board:
        d = {k: v for k, v in asdict(self).items() if k != "_cache"}
        d.update(kw)
        return Board(**d)


def _from_ours(d: dict[str, Any], path: Any) -> Board:
    check_schema(d.get("schema"), BOARD_SCHEMA, (BOARD_VERSION,), path)
    check_keys(d, _KEYS, None, path, name_key=True)
    kind = d.get("kind")
    if kind not in BOARD_KINDS:
        raise FormatError(path, "kind", f"is {kind!r}; valid: {list(BOARD_KINDS)}.", "")
    gkey = {"charuco": "squares", "checkerboard": "inner_corners", "aruco_grid": "markers"}[kind]
    if gkey not in d:
        raise FormatError(path, gkey, f"is missing; a {kind} board needs {gkey} = [columns, rows].", "")
    try:
        return Board(
            kind=kind,
            grid=tuple(d[gkey]),
            square_size_m=float(d.get("square_size_m", 0.0)),
            marker_size_m=float(d.get("marker_size_m", 0.0)),
            marker_separation_m=float(d.get("marker_separation_m", 0.0)),
            dictionary=str(d.get("dictionary", "DICT_4X4_50")),
            legacy_pattern=bool(d.get("legacy_pattern", False)),
            inverted=bool(d.get("inverted", False)),
            name=str(d.get("name", "")),
        )
    except (ValueError, TypeError) as e:
        raise FormatError(
            path, None, str(e), "Fix the board file (see calibrate/boards.py for the format)."
        ) from e


_CALISCOPE_KEYS = (
    "columns",
    "rows",
    "board_height",
    "board_width",
    "dictionary",
    "units",
    "aruco_scale",
    "square_size_override_cm",
    "inverted",
    "legacy_pattern",
)


def _from_caliscope(d: dict[str, Any], path: Any) -> Board:
    """caliscope's charuco.toml: CharucoBoard((columns, rows), square, aruco_scale * square)."""
    check_keys(
        d, _CALISCOPE_KEYS, None, path, fix="A caliscope charuco.toml has these keys only.", name_key=True
    )
    cols, rows = int(d["columns"]), int(d["rows"])
    sq_cm = d.get("square_size_override_cm")
    if sq_cm is None:
        # caliscope: the square size follows from the printed board size
        unit = {"inch": 0.0254, "cm": 0.01, "mm": 0.001, "m": 1.0}.get(str(d.get("units", "inch")))
        if unit is None:
            raise FormatError(path, "units", f"unknown unit {d.get('units')!r}.", "Use inch, cm, mm or m.")
        sq_m = min(float(d["board_width"]) / cols, float(d["board_height"]) / rows) * unit
    else:
        sq_m = round(float(sq_cm) / 100.0, 12)
    try:
        return Board(
            kind="charuco",
            grid=(cols, rows),
            square_size_m=sq_m,
            marker_size_m=sq_m * float(d.get("aruco_scale", 0.75)),
            dictionary=str(d.get("dictionary", "DICT_4X4_50")),
            legacy_pattern=bool(d.get("legacy_pattern", False)),
            inverted=bool(d.get("inverted", False)),
            name=f"caliscope:{Path(str(path)).name}" if path else "caliscope",
        )
    except ValueError as e:
        raise FormatError(path, None, str(e), "") from e


def load_board(path: str | os.PathLike) -> Board:
    """Read a board file: this project's ``board/1`` TOML or caliscope's ``charuco.toml``."""
    d = load_toml(path)
    if "schema" in d:
        return _from_ours(d, path)
    if "columns" in d and "rows" in d:
        return _from_caliscope(d, path)
    raise FormatError(
        path,
        None,
        'is neither a roomcap board file (schema = "board/1") nor a caliscope '
        "charuco.toml (columns, rows, dictionary, ...).",
        'See calibrate/boards.py for the format, e.g. schema="board/1", kind="charuco", '
        'squares=[5,7], square_size_m=0.04, marker_size_m=0.03, dictionary="DICT_4X4_50".',
    )


def save_board(path: str | os.PathLike, board: Board) -> None:
    save_toml(path, board.to_dict(), header=f"roomcap calibration board: {board.describe()}")
