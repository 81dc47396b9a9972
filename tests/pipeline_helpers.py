"""Shared by the pipeline tests: a session output folder's stage outputs, to compare two runs."""

from __future__ import annotations

from pathlib import Path


def stage_outputs(root: Path) -> dict[str, bytes]:
    """Every stage output under an output folder (bookkeeping under .roomcap and summaries excluded)."""
    return {
        p.relative_to(root).as_posix(): p.read_bytes()
        for p in sorted(root.rglob("*"))
        if p.is_file() and ".roomcap" not in p.parts and not p.name.startswith("reprocess_summary")
    }
