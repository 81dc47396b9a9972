"""The action-label file of a session: ``track_id,start_s,end_s,label`` (CSV with that header; seconds from
the session's first frame), one row per labelled action of one tracked person.

>>> import io
>>> rows = read_labels(io.StringIO("track_id,start_s,end_s,label\\n0,0.0,1.5,walk\\n0,1.5,3.0,sit\\n"))
>>> [(r.track_id, r.label) for r in rows]
[(0, 'walk'), (0, 'sit')]
"""

from __future__ import annotations

import csv
import io
import os
from dataclasses import dataclass

from roomcap.core.errors import FormatError

HEADER = ("track_id", "start_s", "end_s", "label")


@dataclass(frozen=True)
class LabelRow:
    track_id: int
    start_s: float
    end_s: float
    label: str
    line: int  # line in the file (1 = header)


def read_labels(src: str | os.PathLike | io.TextIOBase) -> list[LabelRow]:
    """Parse and check a label file: the exact header, numbers, start < end, and no two rows of one track
    that overlap. Raises FormatError naming the file, the line and the fix."""
    name = getattr(src, "name", None) or str(src)
    if isinstance(src, (str, os.PathLike)):
        try:
            with open(src, newline="", encoding="utf-8") as fh:
                text = fh.read()
        except FileNotFoundError:
            raise FormatError(name, None, "no such label file") from None
    else:
        text = src.read()
    reader = csv.reader(io.StringIO(text))
    rows = [r for r in reader if any(c.strip() for c in r)]
    if not rows or tuple(c.strip() for c in rows[0]) != HEADER:
        got = ",".join(rows[0]) if rows else "(empty file)"
        raise FormatError(name, None, f"the first line must be the header {','.join(HEADER)}, got {got!r}")
    out = []
    for i, r in enumerate(rows[1:], start=2):
        if len(r) != 4:
            raise FormatError(
                name, None, f"line {i}: expected 4 fields {','.join(HEADER)}, got {len(r)}: {r}"
            )
        try:
            tid, a, b = int(r[0]), float(r[1]), float(r[2])
        except ValueError:
            raise FormatError(
                name,
                None,
                f"line {i}: track_id must be an integer and start_s, end_s numbers "
                f"(seconds from the session's first frame), got {r[:3]}",
            ) from None
        label = r[3].strip()
        if not label:
            raise FormatError(name, None, f"line {i}: empty label")
        if not (b > a >= 0):
            raise FormatError(name, None, f"line {i}: need 0 <= start_s < end_s, got {a} .. {b}")
        out.append(LabelRow(tid, a, b, label, i))
    if not out:
        raise FormatError(name, None, "no labels after the header")
    by_track: dict[int, list[LabelRow]] = {}
    for r in out:
        by_track.setdefault(r.track_id, []).append(r)
    for tid, rs in by_track.items():
        rs.sort(key=lambda r: r.start_s)
        for p, q in zip(rs[:-1], rs[1:], strict=True):
            if q.start_s < p.end_s:
                raise FormatError(
                    name,
                    None,
                    f"track {tid}'s labels overlap: line {p.line} ({p.label} {p.start_s}-{p.end_s} s) "
                    f"and line {q.line} ({q.label} {q.start_s}-{q.end_s} s); one person does one action at a "
                    "time, so end one before the next starts",
                )
    return out
