"""The warnings the stages logged and the plain-language problems the report lists, with what to do."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from roomcap.capture.session import SessionLayout
from roomcap.pipeline.provenance import STAGES
from roomcap.pipeline.report.inputs import _Inputs


def warnings_path(root: Path, stage: str) -> Path:
    """Where the runner keeps the warnings a stage logged when it last ran (a JSON list of strings)."""
    return Path(root) / ".roomcap" / "warnings" / f"{stage}.json"


def _warnings(lay: SessionLayout) -> list[dict[str, str]]:
    """The warnings the pipeline logged while making the current outputs, by stage (the runner saves
    them per stage; sessions processed before that show the last run's summary)."""

    out: list[dict[str, str]] = []
    seen = set()
    for stage in STAGES:
        try:
            msgs = json.loads(warnings_path(lay.root, stage).read_text())
        except (OSError, json.JSONDecodeError):
            continue
        for m in msgs if isinstance(msgs, list) else []:
            if str(m) not in seen:
                seen.add(str(m))
                out.append({"stage": stage, "message": str(m)})
    if not out:
        try:
            for m in json.loads((lay.root / ".roomcap" / "summary.json").read_text()).get("warnings", []):
                if str(m) not in seen:
                    seen.add(str(m))
                    out.append({"stage": "", "message": str(m)})
        except (OSError, json.JSONDecodeError, AttributeError):
            pass
    return out


def _problem(level: str, title: str, detail: str, action: str) -> dict[str, str]:
    return {"level": level, "title": title, "detail": detail, "action": action}


def _problems(data: dict[str, Any], inp: _Inputs) -> list[dict[str, str]]:
    """A plain-language list of what looks wrong in this session and what to do about each."""
    rig, T = data["rig"], data["tracks"]
    return [
        *_input_problems(rig, T, inp),
        *_detection_rate_problems(data["detections"]),
        *_quality_problems(data["quality"]),
        *_track_problems(T),
        *_calibration_problems(rig),
        *_warning_problems(data["warnings"]),
        *_video_problems(data["views"]),
    ]


def _input_problems(
    rig: dict[str, Any] | None, T: dict[str, Any] | None, inp: _Inputs
) -> list[dict[str, str]]:
    """Missing or unreadable inputs."""
    P: list[dict[str, str]] = []
    if rig is None:
        P.append(
            _problem(
                "error",
                "No calibration",
                "calib/rig.toml is missing.",
                "Calibrate the rig or import a calibration.",
            )
        )
    elif rig.get("error"):
        P.append(_problem("error", "Calibration unreadable", rig["error"], "Fix or replace calib/rig.toml."))
    for cam, msg in (inp.detections_error or {}).items():
        P.append(_problem("error", f"Detections of {cam} unreadable", msg, "Rerun the keypoints stage."))
    if not inp.detections:
        P.append(
            _problem(
                "error", "No 2D detections", "keypoints/ has no detection files.", "Run the keypoints stage."
            )
        )
    for name, err in (("poses3d.npz", inp.poses_error), (inp.tracks_name, inp.tracks_error)):
        if err:
            P.append(
                _problem("error", f"{name} unreadable", err, "Rerun the stage that writes it (--force).")
            )
    if T is None and not inp.tracks_error:
        P.append(
            _problem(
                "error", "No tracks", "track/tracks.npz is missing.", "Run the triangulate and track stages."
            )
        )
    return P


def _detection_rate_problems(detections: dict[str, Any]) -> list[dict[str, str]]:
    """A camera that rarely finds anyone while the others do."""
    P: list[dict[str, str]] = []
    rates = {
        c: float(np.mean(np.asarray(d["people"]) > 0)) if d["people"] else 0.0 for c, d in detections.items()
    }
    if len(rates) > 1:
        best = max(rates.values())
        for c, r in rates.items():
            if best > 0.3 and r < 0.5 * best:
                P.append(
                    _problem(
                        "warning",
                        f"{c} rarely sees anyone",
                        f"people were detected in {100 * r:.0f}% of its frames (best camera: "
                        f"{100 * best:.0f}%).",
                        f"Look at {c}'s filmstrip: if the room is outside its view, aim it at the capture "
                        "area; if people "
                        "are visible but not detected, check focus, exposure and that the lens is not "
                        "covered.",
                    )
                )
    return P


def _quality_problems(Q: dict[str, Any] | None) -> list[dict[str, str]]:
    """Reprojection errors, little-used cameras, joints seen by few cameras or fitting worse."""
    P: list[dict[str, str]] = []
    if Q and not Q.get("error"):
        cams = [c for c in Q["cameras"] if c["mean_px"] is not None]
        if cams:
            med = float(np.median([c["mean_px"] for c in cams]))
            for c in cams:
                others = [o["mean_px"] for o in cams if o is not c]
                ref = float(np.median(others)) if others else med
                if c["mean_px"] > 8.0 or (c["mean_px"] > 4.0 and c["mean_px"] > 2.0 * ref):
                    P.append(
                        _problem(
                            "warning",
                            f"{c['name']}: large reprojection error",
                            f"the 3D lands {c['mean_px']:.1f} px from {c['name']}'s detections on average "
                            f"(other cameras {ref:.1f} px).",
                            "Compare the dots (reprojection) with the skeletons (detections) in "
                            f"{c['name']}'s filmstrip: "
                            "a steady offset means the camera moved or its calibration is off (recalibrate "
                            "it); an "
                            "offset that follows the motion means its video is out of sync (fix the sync "
                            "offset).",
                        )
                    )
            for c in Q["cameras"]:
                if len(Q["cameras"]) > 2 and (c["share"] or 0) < 0.2 and Q["n_joints_3d"] > 0:
                    P.append(
                        _problem(
                            "warning",
                            f"{c['name']} is rarely used",
                            f"its view went into {100 * (c['share'] or 0):.0f}% of the triangulated joints.",
                            "It may see little of the capture area, or its detections disagree with the "
                            "other cameras "
                            "(calibration or sync): check its filmstrip.",
                        )
                    )
        if Q.get("per_camera_note"):
            P.append(_problem("info", "No per-camera errors", Q["per_camera_note"], "Rerun triangulate."))
        pv = [v for v in Q["per_joint_views"] if v is not None]
        if pv and float(np.mean(pv)) < 2.5 and len(Q["cameras"]) > 2:
            P.append(
                _problem(
                    "info",
                    "Joints seen by few cameras",
                    f"a triangulated joint was seen by {float(np.mean(pv)):.1f} cameras on average.",
                    "Two views give little redundancy against a wrong detection: add cameras or aim them "
                    "so each "
                    "part of the room is seen by three or more.",
                )
            )
        pj = Q["per_joint_mean_px"]
        vals = [v for v in pj if v is not None]
        if vals:
            m = float(np.mean(vals))
            worst = [Q["joint_names"][j] for j, v in enumerate(pj) if v is not None and v > max(2.0 * m, 6.0)]
            if worst:
                P.append(
                    _problem(
                        "info",
                        "Some joints fit worse than the rest",
                        f"{', '.join(worst)}: more than twice the mean error ({m:.1f} px).",
                        "Usual for fast or often occluded joints (wrists, ankles); if it is a hip or "
                        "shoulder, the 2D "
                        "model may confuse left and right or the skeleton definitions differ between views.",
                    )
                )
    return P


def _track_problems(T: dict[str, Any] | None) -> list[dict[str, str]]:
    """Tracks carried unseen, sudden jumps and swaps, fragmented identities."""
    P: list[dict[str, str]] = []
    if T is not None:
        ev = T["events"]
        fps_full = T["fps"] * T["step"]
        for k, tid in enumerate(T["track_id"]):
            pres, un = ev["present_frames"][k], ev["unobserved_frames"][k]
            if pres and un / pres > 0.1 and un / fps_full >= 0.5:
                P.append(
                    _problem(
                        "info",
                        f"id {tid} carried without being seen",
                        f"{un / fps_full:.1f} s of its {pres / fps_full:.1f} s ({100 * un / pres:.0f}%) "
                        "were predicted or "
                        "interpolated, not observed.",
                        "Its positions there are guesses (hatched in the timeline): if it was in view, the "
                        "detections "
                        "missed it (occlusion, low light); if not, more camera coverage would help.",
                    )
                )
        jumps = ev["jumps"]
        if jumps:
            swaps = [j for j in jumps if j["swap_with"] is not None]
            where = ", ".join(
                f"id {j['id']} at frame {j['frame']} ({j['dist_m']:.2f} m"
                + (f", to where id {j['swap_with']} was" if j["swap_with"] is not None else "")
                + ")"
                for j in jumps[:6]
            )
            P.append(
                _problem(
                    "warning",
                    f"{len(jumps)} sudden jump{'s' if len(jumps) > 1 else ''}"
                    + (
                        f", {len(swaps)} suspected identity swap{'s' if len(swaps) > 1 else ''}"
                        if swaps
                        else ""
                    ),
                    where + (" …" if len(jumps) > 6 else "") + ".",
                    "Check those frames in the filmstrips (red marks on the timeline): if two people "
                    "crossed, their "
                    "identities may have been exchanged; the particle tracker (--tracker particle) keeps "
                    "identities "
                    "better through crossings. A jump of one person alone is usually a wrong 3D pose (bad "
                    "association).",
                )
            )
        people = (
            max((sum(1 for v in col if v) for col in zip(*T["present"], strict=True)), default=0)
            if T["present"]
            else 0
        )
        if people and len(T["track_id"]) > 2 * people + 1:
            P.append(
                _problem(
                    "info",
                    "Identities fragmented",
                    f"{len(T['track_id'])} tracks for at most {people} people at once.",
                    "People lost and found again get new ids: check the timeline for short tracks; longer "
                    "occlusion "
                    "handling (tracker options) or more coverage helps.",
                )
            )
    return P


def _calibration_problems(rig: dict[str, Any] | None) -> list[dict[str, str]]:
    """The calibration's own RMS errors."""
    P: list[dict[str, str]] = []
    figs = (rig or {}).get("figures") or {}
    if figs.get("unit") == "px":
        for cam, f in figs.get("cameras", {}).items():
            for key in ("intrinsic_rms_px", "extrinsic_rms_px"):
                if key in f and f[key] > 1.0:
                    P.append(
                        _problem(
                            "warning",
                            f"{cam}: calibration {key.split('_')[0]} RMS {f[key]:.2f} px",
                            "above 1 px, its 3D will be less accurate.",
                            "Recalibrate with more board views covering the whole image.",
                        )
                    )
    return P


def _warning_problems(warnings: list[dict[str, str]]) -> list[dict[str, str]]:
    """The stages' warnings that call for an action (video size, video lengths)."""
    P: list[dict[str, str]] = []
    size = [w["message"] for w in warnings if "calibration" in w["message"] and "video" in w["message"]]
    if size:
        P.append(
            _problem(
                "warning",
                "Video size differs from the calibration"
                + (f" ({len(size)} cameras)" if len(size) > 1 else ""),
                "; ".join(size),
                "The keypoints are used as they are (codec padding). If the overlays look shifted or "
                "scaled, recalibrate at the video's resolution.",
            )
        )
    for w in warnings:
        if "differ in length" in w["message"]:
            P.append(
                _problem(
                    "warning",
                    "Videos of different length",
                    w["message"],
                    "Check the sync: trim the videos to a common start.",
                )
            )
    return P


def _video_problems(V: dict[str, Any] | None) -> list[dict[str, str]]:
    """Videos the filmstrips could not read."""
    P: list[dict[str, str]] = []
    if V:
        for c in V["cameras"]:
            if c.get("note") and c["note"].startswith("video") and "could not be read" in c["note"]:
                P.append(
                    _problem("info", f"{c['name']}: video unreadable", c["note"], "Check the video file.")
                )
    return P
