"""One interface for the benchmark protocols: ``evaluate()`` into one results.json schema, one renderer.

A protocol (:class:`Protocol`) has a ``name`` and ``evaluate(**options) -> dict``. The dict holds the
protocol's own figures (``models``, ``actions``, ... as its tests and users read them) and the fields of the
one schema (:data:`RESULTS_SCHEMA`), filled by :func:`results`:

* ``schema``, ``protocol`` (its name) and ``title``;
* ``notes``: lines of Markdown above the tables (reference, data missing, units);
* ``tables``: each ``{"title", "columns", "rows"}``, rows of cells already written as text;
* ``footer``: lines below the tables (sources).

:func:`render` is the one Markdown renderer and :func:`write` writes ``results.json`` and ``report.md``.
Every protocol uses it: the CMU splits (``forecast eval --data``), the CMU 8-action benchmark (3D and
angles), Humans-in-Kitchens, the salsa pairs, characteristic poses and behaviour; :data:`PROTOCOLS` lists
them and the module whose ``as_results`` or ``evaluate`` fills the schema.
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Protocol as TypingProtocol

from roomcap.core.errors import FormatError
from roomcap.core.fileio import atomic_write_text

RESULTS_SCHEMA = "forecast-results/1"

# every benchmark protocol: name -> (what it is, the module that fills the schema, on the interface)
PROTOCOLS = {
    "cmu8": ("the CMU 8-action benchmark, MPJPE (LTD's protocol)", "benchmark_cmu8", True),
    "cmu8-all": (
        "the CMU 8-action benchmark, MPJPE on every test window (MSR-GCN, PGBIG)",
        "benchmark_cmu8",
        True,
    ),
    "cmu8-angle": (
        "the CMU 8-action benchmark, mean angle error (Tanke Table 6.7)",
        "benchmark_cmu8_angle",
        True,
    ),
    "hik": ("Humans in Kitchens (Tanke ch. 8.3)", "hik", True),
    "cmu": ("CMU test split: NDMS, MPJPE, diversity (Tanke ch. 6)", "evaluate", True),
    "pairs": ("the held-out salsa pairs (two people)", "pairs", True),
    "characteristic": ("characteristic 3D poses, best-of-k (Diller ch. 3)", "characteristic.cli", True),
    "behaviour": ("behaviour: actions and poses (Diller ch. 4)", "behaviour.training", True),
}


class Protocol(TypingProtocol):
    """What every benchmark protocol offers."""

    name: str

    def evaluate(self, **options) -> dict: ...


@dataclass(frozen=True)
class Table:
    title: str
    columns: Sequence[str]
    rows: Sequence[Sequence[str]]


def results(
    protocol: str,
    title: str,
    notes: Sequence[str],
    tables: Sequence[Table],
    footer: Sequence[str] = (),
    **fields,
) -> dict:
    """A results dict of the one schema: the protocol's own ``fields`` and its report's notes and tables."""
    return {
        "schema": RESULTS_SCHEMA,
        "protocol": protocol,
        "title": title,
        **fields,
        "notes": list(notes),
        "tables": [asdict(t) | {"rows": [list(r) for r in t.rows]} for t in tables],
        "footer": list(footer),
    }


def cells(values: Sequence[float | None], fmt: str = ".1f") -> list[str]:
    """Numbers as table cells ("-" for None)."""
    return ["-" if v is None else format(v, fmt) for v in values]


def render(res: dict) -> str:
    """The one Markdown renderer: the title, the notes, every table under its heading, the footer."""
    if res.get("schema") != RESULTS_SCHEMA:
        raise FormatError("results", "schema", f"expected '{RESULTS_SCHEMA}', got {res.get('schema')!r}.", "")
    lines = [f"# {res['title']}", ""]
    for n in res["notes"]:
        lines += [n, ""]
    for t in res["tables"]:
        if t["title"]:
            lines += [f"## {t['title']}", ""]
        lines.append("| " + " | ".join(t["columns"]) + " |")
        lines.append("|" + "---|" * len(t["columns"]))
        lines += ["| " + " | ".join(r) + " |" for r in t["rows"]]
        lines.append("")
    lines += list(res.get("footer", []))
    return "\n".join(lines).rstrip("\n") + "\n"


def write(res: dict, out_dir: str | os.PathLike) -> Path:
    """``results.json`` and ``report.md`` (:func:`render`) in ``out_dir``; -> the report's path."""
    d = Path(out_dir)
    d.mkdir(parents=True, exist_ok=True)
    atomic_write_text(d / "results.json", json.dumps(res, indent=1))
    path = d / "report.md"
    atomic_write_text(path, render(res))
    return path
