"""Model cards of the shipped checkpoints (``forecast models``): what each file is and what it was made from,
read from the checkpoint itself (every schema of :data:`forecast.runtime.checkpoint.KNOWN_SCHEMAS`): the
model, skeleton, rate and observation, the data split it was trained and selected on, its selection rule and
validation scores, and the command that made it where the file records one. Importing this module loads
torch.
"""

from __future__ import annotations

import os
from pathlib import Path

import torch

from roomcap.forecast.runtime.checkpoint import KNOWN_SCHEMAS, describe_checkpoint
from roomcap.forecast.runtime.preview import CHECKPOINT_DIR, DEFAULT_CHECKPOINT
from roomcap.forecast.runtime.registry import MODELS


def card(path: str | os.PathLike) -> dict:
    """The card of one checkpoint file (any schema; an unreadable file's card says why)."""
    path = Path(path)
    c: dict = {"file": path.name, "size_kb": round(path.stat().st_size / 1024)}
    c["default"] = path.resolve() == Path(DEFAULT_CHECKPOINT).resolve()
    try:
        blob = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 - a card says what is wrong with the file
        return {**c, "what": f"not readable ({type(e).__name__})"}
    c["schema"] = blob.get("schema") if isinstance(blob, dict) else None
    if c["schema"] not in KNOWN_SCHEMAS:
        return {**c, "what": describe_checkpoint(blob)}
    c["what"], c["reads_it"] = KNOWN_SCHEMAS[c["schema"]]
    if blob.get("representation") == "expmap":  # the benchmark's exponential maps (Tanke Table 6.7's metric)
        c["what"] = "a DCT + MLP of the CMU 8-action benchmark's exponential maps at 60 Hz (not tracks)"
        c["reads_it"] = "`forecast eval --protocol cmu8 --metric angle --checkpoints PATH` scores it"
    kind = blob.get("kind")
    if kind in MODELS:
        c["model"] = f"{kind}: {MODELS[kind].summary}"
    elif isinstance(kind, str):
        c["model"] = kind
    for key in ("skeleton", "fps"):
        if key in blob:
            c[key] = blob[key]
    cfg = blob.get("config") if isinstance(blob.get("config"), dict) else {}
    if "n_obs" in cfg and "fps" in blob:
        c["observes"] = f"{cfg['n_obs']} frames ({cfg['n_obs'] / float(blob['fps']):.1f} s)"
    extra = blob.get("extra") or blob.get("meta") or {}
    c.update(_data(extra))
    return c


def _data(extra: dict) -> dict:
    """The split, selection and provenance a checkpoint's ``extra`` records."""
    out: dict = {}
    n = {k: len(extra[f"{k}_clips"]) for k in ("train", "val", "test") if f"{k}_clips" in extra}
    if n:
        out["data"] = ", ".join(f"{v} {k} clips" for k, v in n.items()) + " (split by clip; test held out)"
    if extra.get("val_files"):
        out["data"] = f"the benchmark's train files; validation {len(extra['val_files'])} files"
    vb = extra.get("val_best") or {}
    if vb:
        out["selection"] = (
            f"step {vb['step']} by validation {vb.get('select', '?')}: NDMS 2-4 s {vb['ndms_2_4']:.3f}, "
            f"MPJPE 0-1 s {1000 * vb['mpjpe_0_1']:.0f} mm"
        )
    elif isinstance(extra.get("best"), dict) and "val_mm" in extra["best"]:
        out["selection"] = f"validation MPJPE {extra['best']['val_mm']:.1f} mm (the benchmark's units)"
    elif isinstance(extra.get("best"), dict) and "val_rad" in extra["best"]:
        b = extra["best"]
        out["selection"] = f"step {b['step']} by validation mean angle error {b['val_rad']:.3f} rad"
    if extra.get("members"):
        out["members"] = ", ".join(extra["members"])
    if extra.get("init"):
        out["init"] = extra["init"]
    if extra.get("command"):
        out["command"] = extra["command"]
    return out


def cards(folder: str | os.PathLike = CHECKPOINT_DIR) -> list[dict]:
    """The cards of every ``*.pt`` in ``folder`` (default: the shipped ones), by name."""
    return [card(p) for p in sorted(Path(folder).glob("*.pt"))]


FIELDS = ("what", "model", "skeleton", "fps", "observes", "data", "selection", "members", "init", "command")


def render(cs: list[dict]) -> str:
    """The cards as text: one block per file, the default checkpoint marked."""
    lines = []
    for c in cs:
        mark = "  (the default of forecast sample and the pipeline's preview)" if c.get("default") else ""
        lines.append(f"{c['file']}  [{c.get('schema')}, {c['size_kb']} kB]{mark}")
        lines += [f"    {k}: {c[k]}" for k in FIELDS if k in c]
        if "reads_it" in c:
            lines.append(f"    use: {c['reads_it'].replace('PATH', 'forecast/checkpoints/' + c['file'])}")
        lines.append("")
    return "\n".join(lines)
