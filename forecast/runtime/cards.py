"""Model cards of the shipped checkpoints (``forecast models``): what each file is and what it was made from,
read from the checkpoint itself (the ``card`` of the one format, :mod:`roomcap.forecast.runtime.checkpoint`;
an older schema is upgraded on read): the model, skeleton, rate and observation, the data and split it was
trained and selected on, its selection rule, validation scores and the command that made and measured it.
"""

from __future__ import annotations

import os
from pathlib import Path

from roomcap.core.errors import FormatError
from roomcap.forecast.runtime.checkpoint import read_checkpoint
from roomcap.forecast.runtime.preview import CHECKPOINT_DIR, DEFAULT_CHECKPOINT
from roomcap.forecast.runtime.registry import FAMILIES


def card(path: str | os.PathLike) -> dict:
    """The card of one checkpoint file (an unreadable or foreign file's card says what it is)."""
    path = Path(path)
    c: dict = {"file": path.name, "size_kb": round(path.stat().st_size / 1024)}
    c["default"] = path.resolve() == Path(DEFAULT_CHECKPOINT).resolve()
    try:
        blob = read_checkpoint(path)
    except FormatError as e:  # a card says what is wrong with the file
        return {**c, "what": str(e)}
    fam = FAMILIES[blob["model"]]
    schema = blob["schema"] + (f", upgraded from {blob['upgraded_from']}" if "upgraded_from" in blob else "")
    c |= {"schema": schema, "model": fam.name, "what": fam.what, "reads_it": fam.reads_it}
    for key in ("skeleton", "fps"):
        if key in blob:
            c[key] = blob[key]
    cfg = blob.get("config") if isinstance(blob.get("config"), dict) else {}
    cfg = (cfg.get("members") or [cfg])[0]  # an ensemble's members observe alike
    if "n_obs" in cfg and "fps" in blob:
        c["observes"] = f"{cfg['n_obs']} frames ({cfg['n_obs'] / float(blob['fps']):.1f} s)"
    return c | {k: v for k, v in blob["card"].items() if v}


def cards(folder: str | os.PathLike = CHECKPOINT_DIR) -> list[dict]:
    """The cards of every ``*.pt`` in ``folder`` (default: the shipped ones), by name."""
    return [card(p) for p in sorted(Path(folder).glob("*.pt"))]


FIELDS = ("what", "model", "skeleton", "fps", "observes", "data", "split", "selection", "scores", "command")


def render(cs: list[dict]) -> str:
    """The cards as text: one block per file, the default checkpoint marked."""
    lines = []
    for c in cs:
        mark = "  (the default of forecast sample and the pipeline's preview)" if c.get("default") else ""
        lines.append(f"{c['file']}  [{c.get('schema')}, {c['size_kb']} kB]{mark}")
        for k in FIELDS:
            if k in c:
                v = c[k]
                if isinstance(v, dict):
                    v = ", ".join(
                        f"{a} {b:.4g}" if isinstance(b, float) else f"{a} {b}" for a, b in v.items()
                    )
                lines.append(f"    {k}: {v}")
        if "reads_it" in c:
            lines.append(f"    use: {c['reads_it'].replace('PATH', 'forecast/checkpoints/' + c['file'])}")
        lines.append("")
    return "\n".join(lines)
