"""The one checkpoint format of every forecasting family, its one writer and one reader, and the converter of
the older formats.

A checkpoint (``torch.save`` of plain containers, read with ``weights_only=True``) is a dict:

* ``schema = "forecast-checkpoint/2"``, ``model``: a family of :data:`registry.FAMILIES` (the track models
  ``gru``, ``intention``, ``social_diffusion``; ``characteristic``, ``cmu8_dct_mlp``, ``cmu8_angle_dct_mlp``,
  ``behaviour``, ``behaviour_quality``);
* ``config``: the model's config as a dict (a family of several networks keeps one per network);
* ``weights``: named state dicts (``model``; ``det`` beside it for the characteristic model; ``member<i>`` of
  an ensemble; one per variant of the behaviour model);
* ``card``: the model card: ``data`` and ``split`` it was trained and selected on, the ``selection`` rule,
  the validation ``scores`` and the ``command`` that trained it and measured them;
* ``extra``: the training's own record (the clips of each split, history);
* what else the family needs to use it: ``skeleton``, ``joint_names``, ``fps``, ``normalisation`` (Tanke eq.
  3.8) for the track models; the benchmark's ``points`` and ``units`` for the CMU 8-action models, ...

The five schemas before it (``forecast-checkpoint/1``, ``forecast-characteristic/1``,
``forecast-cmu8-checkpoint/1``, ``behaviour_checkpoint/1``, ``behaviour_quality/1``) are upgraded on read,
with a note; ``forecast models --convert OLD NEW`` rewrites such a file. Importing this module does not load
torch: reading or writing a file does.
"""

from __future__ import annotations

import dataclasses
import logging
import os
from pathlib import Path
from typing import Any

from roomcap.core.errors import FormatError, InputError
from roomcap.core.fileio import atomic_path
from roomcap.forecast.runtime.normalise import LHIP, RHIP, TARGET_FPS
from roomcap.forecast.runtime.registry import (
    DISCRIMINATOR_PREFIXES,
    FAMILIES,
    MODELS,
    build_model,
    config_from_dict,
)
from roomcap.forecast.runtime.registry import (
    baseline as baseline_spec,
)

log = logging.getLogger(__name__)

SCHEMA = "forecast-checkpoint/2"
NORMALISATION = "eq. 3.8 at the last observed frame: root = mid-hips, hip vector (left->right) on +x, z up"
CARD_FIELDS = ("data", "split", "selection", "scores", "command")

# the schemas before the one format: schema -> what it was (the converter reads them)
LEGACY = {
    "forecast-checkpoint/1": "a forecast checkpoint (GRU, intention or Social Diffusion) of the first format",
    "forecast-characteristic/1": "a characteristic-3D-pose checkpoint of the first format",
    "forecast-cmu8-checkpoint/1": "a CMU 8-action DCT + MLP checkpoint of the first format",
    "behaviour_checkpoint/1": "a behaviour checkpoint of the first format",
    "behaviour_quality/1": "a behaviour pose-quality checkpoint of the first format",
}


def _plain(config) -> Any:
    """A config as builtins: a dataclass as its dict, a dict or list of them (one per network) likewise."""
    if dataclasses.is_dataclass(config):
        return dataclasses.asdict(config)
    if isinstance(config, dict):
        return {k: _plain(v) for k, v in config.items()}
    if isinstance(config, (list, tuple)):
        return [_plain(v) for v in config]
    return config


def write_checkpoint(
    path: str | os.PathLike,
    model: str,
    *,
    config,
    weights: dict,
    card: dict | None = None,
    extra: dict | None = None,
    **fields,
) -> None:
    """Write a checkpoint of family ``model`` atomically: ``config`` (a dataclass, or a dict of them),
    ``weights`` (name -> state dict; tensors are detached to the CPU), the model ``card`` (default: read from
    ``extra``, see :func:`card_from_extra`), ``extra`` and the family's ``fields``."""
    import torch  # lazy: loads torch

    if model not in FAMILIES:
        raise InputError(f"unknown model family '{model}'; the families: {sorted(FAMILIES)}")
    extra = dict(extra or {})
    blob = {
        "schema": SCHEMA,
        "model": model,
        "config": _plain(config),
        "weights": {
            n: {k: v.detach().cpu() if isinstance(v, torch.Tensor) else v for k, v in sd.items()}
            for n, sd in weights.items()
        },
        "card": card if card is not None else card_from_extra(extra),
        "extra": extra,
        **fields,
    }
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        torch.save(blob, tmp)


def describe_checkpoint(blob) -> str:
    """What a loaded file ``blob`` is, in words: a checkpoint of a known family (and what reads it), one of an
    older schema (and how to convert it), one of a model this version does not know, or something else."""
    import torch  # lazy: loads torch

    if not isinstance(blob, dict):
        return f"a {type(blob).__name__}, not a checkpoint dict"
    schema = blob.get("schema")
    if schema == SCHEMA:
        fam = FAMILIES.get(blob.get("model"))
        if fam is None:
            return (
                f"a checkpoint of model '{blob.get('model')}', which this roomcap version does not know (it "
                f"knows {', '.join(FAMILIES)}): use the version that wrote it, or retrain"
            )
        return f"{fam.what} ('{fam.name}'): {fam.reads_it}"
    if schema in LEGACY:
        return (
            f"{LEGACY[schema]} (schema '{schema}'): it is read with an upgrade on the fly; "
            "`forecast models --convert OLD NEW` rewrites it in the current format"
        )
    if isinstance(schema, str):
        return (
            f"a checkpoint of schema '{schema}', which roomcap does not know (this version writes '{SCHEMA}')"
        )
    if blob and all(isinstance(v, torch.Tensor) for v in blob.values()):
        return (
            f"a bare PyTorch state dict ({len(blob)} tensors, no schema, config or skeleton), so the model "
            "cannot be rebuilt from it: save the model with "
            "roomcap.forecast.runtime.checkpoint.save_checkpoint(model, kind, config), or retrain it"
        )
    return f"a dict without a schema (keys {sorted(map(str, blob))[:6]})"


def read_checkpoint(
    path: str | os.PathLike,
    model: str | tuple[str, ...] | None = None,
    skeleton: str | None = None,
    map_location: str = "cpu",
    missing_as_is: bool = False,
) -> dict:
    """The checkpoint at ``path`` in the current format (an older schema is upgraded, with a note), checked to
    be of family ``model`` (a name or several; None: any) and to fit the caller's data ``skeleton`` (None:
    any); every error names what the file is and how to get a good one. ``missing_as_is``: a missing file
    raises FileNotFoundError, for a caller that words that case itself."""
    import torch  # lazy: loads torch

    path = Path(path)
    wanted = (model,) if isinstance(model, str) else tuple(model or ())
    train = (
        " or ".join(f"`{FAMILIES[m].train}`" for m in wanted if m in FAMILIES) or "the family's train command"
    )
    try:
        blob = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as e:  # noqa: BLE001 - re-raised with what to do
        if missing_as_is and isinstance(e, FileNotFoundError):
            raise
        what = "; ".join(FAMILIES[m].what for m in wanted if m in FAMILIES) or "a forecasting model"
        why = (str(e).strip().splitlines() or [""])[0]
        kind = " or ".join(wanted) + " " if wanted else ""
        raise FormatError(
            path,
            None,
            f"not a readable {kind}checkpoint ({what}; {type(e).__name__}: {why}).",
            f"Train one with {train}.",
        ) from e
    if isinstance(blob, dict) and blob.get("schema") in LEGACY:
        old = blob["schema"]
        try:
            blob = upgrade(blob) | {"upgraded_from": old}
        except (KeyError, TypeError, AttributeError) as e:
            raise FormatError(
                path, "schema", f"{LEGACY[old]}, damaged: it lacks {e}.", f"Retrain: {train}."
            ) from None
        log.warning(
            "%s: schema '%s' upgraded on read to '%s'; `forecast models --convert %s NEW` rewrites it",
            path,
            old,
            SCHEMA,
            path,
        )
    if not isinstance(blob, dict) or blob.get("schema") != SCHEMA or blob.get("model") not in FAMILIES:
        raise FormatError(path, "schema", f"this is {describe_checkpoint(blob)}.", f"Train one with {train}.")
    if wanted and blob["model"] not in wanted:
        raise FormatError(
            path,
            "model",
            f"a '{blob['model']}' checkpoint, not {' or '.join(repr(m) for m in wanted)}: "
            f"{describe_checkpoint(blob)}.",
            f"Train one with {train}.",
        )
    if skeleton is not None and blob.get("skeleton", skeleton) != skeleton:
        raise FormatError(
            path,
            "skeleton",
            f"the checkpoint was trained on skeleton '{blob['skeleton']}' "
            f"({len(blob['joint_names'])} joints) but the data is '{skeleton}'.",
            f"Convert the data to '{blob['skeleton']}' or train a model on '{skeleton}'.",
        )
    return blob


def family_of(path: str | os.PathLike) -> str | None:
    """The family (``model``) of the checkpoint at ``path``, an older schema's included; None for a file that
    is not a checkpoint of a known family (unreadable, another format)."""
    import torch  # lazy: loads torch

    try:
        blob = torch.load(path, map_location="cpu", weights_only=True)
    except Exception:  # noqa: BLE001 - not a checkpoint: the caller tries the other readers
        return None
    if isinstance(blob, dict) and blob.get("schema") in LEGACY:
        blob = upgrade(blob)
    ok = isinstance(blob, dict) and blob.get("schema") == SCHEMA and blob.get("model") in FAMILIES
    return blob["model"] if ok else None


# ----------------------------------------------------------------------------- the model card


def card_from_extra(extra: dict) -> dict:
    """The model card a training's ``extra`` records: data and split, the selection rule, the validation
    scores and the command (empty fields left out)."""
    out: dict = {}
    n = {k: len(extra[f"{k}_clips"]) for k in ("train", "val", "test") if f"{k}_clips" in extra}
    if n:
        out["data"] = str(extra.get("data", "clips"))
        out["split"] = ", ".join(f"{v} {k} clips" for k, v in n.items()) + " (by clip; test held out)"
    if extra.get("val_files"):
        out["data"] = "the CMU 8-action benchmark's train files"
        out["split"] = f"validation: the last train file of each action ({len(extra['val_files'])} files)"
    hist = extra.get("history") if isinstance(extra.get("history"), dict) else {}
    vb = extra.get("val_best") or (hist.get("heatmap") or {}).get("val_best") or {}
    best = extra.get("best") if isinstance(extra.get("best"), dict) else {}
    if "ndms_2_4" in vb:
        out["selection"] = (
            f"the step of the best validation {vb.get('select', 'ndms_2_4')} (step {vb['step']})"
        )
        out["scores"] = {"split": "validation", "ndms_2_4": vb["ndms_2_4"], "mpjpe_0_1_m": vb["mpjpe_0_1"]}
    elif "mpjpe_best_of_k" in vb:
        out["data"] = str(extra.get("data", "cmu"))
        out["selection"] = f"the step of the best validation best-of-k MPJPE (step {vb['step']})"
        out["scores"] = {"split": "validation", "mpjpe_best_of_k_m": vb["mpjpe_best_of_k"]}
    elif "val_mm" in best:
        out["selection"] = "the lowest validation MPJPE (the benchmark's units)"
        out["scores"] = {"split": "validation", "mpjpe_units": best["val_mm"]}
    elif "val_rad" in best:
        step = f" (step {best['step']})" if "step" in best else ""  # an ensemble has no step
        out["selection"] = "the lowest validation mean angle error" + step
        out["scores"] = {"split": "validation", "angle_error_rad": best["val_rad"]}
    full = (hist.get("full") or {}) if "action_freq" in extra else {}
    if full:  # the behaviour model: its variants, the full one's validation objective
        out["data"] = "composite activities of labelled CMU clips (the train subjects)"
        out["selection"] = f"the step of the best validation objective (full: step {full['best_step']})"
        best = next((v for v in full.get("val", []) if v.get("step") == full["best_step"]), {})
        keys = ("action_ce", "pose2d", "objective")
        out["scores"] = {"split": "validation", **{k: best[k] for k in keys if k in best}}
    if "share_judged_real" in extra:  # the behaviour pose-quality classifier
        out["data"] = f"{extra['n_real']} database poses against {extra['n_fake']} generated ones"
        out["selection"] = f"the last of {extra.get('clf_steps', '?')} steps (no selection)"
        share = extra["share_judged_real"]
        out["scores"] = {"split": "held-out database", "share_judged_real": share.get("database_held_out")}
    if extra.get("members"):
        out["selection"] = out.get("selection", "") + f"; mean of {len(extra['members'])} members"
    if extra.get("command"):
        out["command"] = extra["command"]
    return out


# ----------------------------------------------------------------------------- the older schemas


def upgrade(blob: dict) -> dict:
    """An older checkpoint (:data:`LEGACY`) in the current format: the same weights, configs and record,
    rearranged (nothing is retrained or rescaled)."""
    schema = blob["schema"]
    extra = dict(blob.get("extra") or blob.get("meta") or {})
    keep = ("skeleton", "joint_names", "fps", "normalisation", "annotator", "avg_pose", "points", "units")
    fields = {k: blob[k] for k in keep if k in blob}
    if schema in ("forecast-checkpoint/1", "forecast-characteristic/1"):
        model = blob.get("kind", "characteristic")
        weights = {"model": blob["state_dict"]}
        if "det_state_dict" in blob:
            weights["det"] = blob["det_state_dict"]
        config = blob["config"]
    elif schema == "forecast-cmu8-checkpoint/1" and blob.get("representation") == "expmap":
        model, config, weights = "cmu8_angle_dct_mlp", blob["config"], {"model": blob["state_dict"]}
        fields |= {"vectors": blob["vectors"], "dims": blob["dims"]}
    elif schema == "forecast-cmu8-checkpoint/1":
        members = blob.get("members") or [{"config": blob["config"], "state_dict": blob["state_dict"]}]
        model = "cmu8_dct_mlp"
        config = {"members": [m["config"] for m in members]}
        weights = {f"member{i}": m["state_dict"] for i, m in enumerate(members)}
    elif schema == "behaviour_checkpoint/1":
        model = "behaviour"
        config = {n: m["config"] for n, m in blob["models"].items()}
        weights = {n: m["state"] for n, m in blob["models"].items()}
        fields["actions"] = blob["actions"]
    else:  # behaviour_quality/1
        model, config, weights = "behaviour_quality", {}, {"model": blob["state"]}
        fields["joints"] = blob["joints"]
    return {
        "schema": SCHEMA,
        "model": model,
        "config": config,
        "weights": weights,
        "card": card_from_extra(extra),
        "extra": extra,
        **fields,
    }


def convert(old: str | os.PathLike, new: str | os.PathLike) -> str:
    """Rewrite the checkpoint ``old`` in the current format at ``new`` (the same weights); -> what it was."""
    import torch  # lazy: loads torch

    try:
        blob = torch.load(old, map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 - re-raised with what to do
        raise FormatError(old, None, f"not a readable checkpoint ({type(e).__name__}: {e}).", "") from e
    if isinstance(blob, dict) and blob.get("schema") == SCHEMA:
        was = f"already '{SCHEMA}' ('{blob.get('model')}')"
    elif isinstance(blob, dict) and blob.get("schema") in LEGACY:
        was = f"'{blob['schema']}' -> '{SCHEMA}'"
        blob = upgrade(blob)
    else:
        raise FormatError(old, "schema", f"this is {describe_checkpoint(blob)}.", "Nothing to convert.")
    with atomic_path(new) as tmp:
        torch.save(blob, tmp)
    return was


# ----------------------------------------------------------------------------- the track models


def save_checkpoint(
    path: str | os.PathLike,
    model,
    kind: str,
    config,
    skeleton: str = "body19",
    fps: float = TARGET_FPS,
    extra: dict | None = None,
) -> None:
    """A track model (:data:`registry.MODELS`) without its training-only weights (the discriminators)."""
    from roomcap.keypoints.skeletons import get_skeleton

    state = {k: v for k, v in model.state_dict().items() if not k.startswith(DISCRIMINATOR_PREFIXES)}
    write_checkpoint(
        path,
        kind,
        config=config,
        weights={"model": state},
        extra=extra,
        skeleton=skeleton,
        joint_names=list(get_skeleton(skeleton).joint_names),
        fps=float(fps),
        normalisation=NORMALISATION,
    )


def load_checkpoint(path: str | os.PathLike, skeleton: str | None = None, map_location: str = "cpu"):
    """-> (model, meta) of a track model. ``skeleton``: the skeleton the caller's data uses; a mismatch is a
    clear error. ``meta`` is the file less its weights, with ``config`` typed."""
    blob = read_checkpoint(Path(path), tuple(MODELS), skeleton, map_location)
    name = blob["model"]
    try:
        config = config_from_dict(name, blob["config"])
    except (InputError, FormatError) as e:
        why = str(e).removeprefix(f"<input>: field '{name} config': ").removesuffix(" Remove or rename them.")
        raise FormatError(
            path,
            "config",
            f"its {name} config does not fit this roomcap version ({why.rstrip('.')}).",
            f"It was written by another version: forecast with that one, or retrain with `forecast train "
            f"--model {name}` (--set the keys above that this version knows).",
        ) from None
    model = build_model(name, config, len(blob["joint_names"]), blob["weights"]["model"])
    meta = {k: v for k, v in blob.items() if k != "weights"}
    meta["config"] = config
    return model.to(map_location), meta


def baseline(kind: str, lhip: int = LHIP, rhip: int = RHIP):
    """The torch module of baseline ``kind`` (:data:`registry.BASELINES`)."""
    return baseline_spec(kind).module(lhip, rhip)
