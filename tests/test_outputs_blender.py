"""Headless Blender imports the BVH export: one armature per person, frames and rate, heads on the fit.

Needs Debian's ``blender`` (``apt-get install -y blender``); skipped with that reason when absent.
"""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from roomcap.outputs.bvh import write_bvh
from roomcap.outputs.skeleton_fit import fit_skeletons
from roomcap.outputs.skeleton_fit_file import SkeletonFit

PROBE = Path(__file__).with_name("blender_bvh_probe.py")


def blender_import(bvh_files: list[Path], out_json: Path) -> dict:
    """Import BVH files in headless Blender; the probe's JSON (see tests/blender_bvh_probe.py)."""
    exe = shutil.which("blender")
    if exe is None:
        pytest.skip("blender is not installed (apt-get install -y blender)")
    cmd = [exe, "-b", "--factory-startup", "--python", str(PROBE), "--", str(out_json), *map(str, bvh_files)]
    run = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0 and out_json.exists(), run.stdout[-2000:] + run.stderr[-2000:]
    return json.loads(out_json.read_text())


def check_armatures(fit: SkeletonFit, files: dict[int, Path], got: dict) -> dict[str, float]:
    """Assert the import matches the fit (one armature per person, frames, rate, bone heads and lengths);
    returns the worst head error and bone length spread (metres)."""
    assert got["n_armatures"] == len(files), "one armature per person"
    P = fit.positions()
    worst_head = worst_len = 0.0
    by_file = {a["file"]: a for a in got["armatures"]}
    for tid, path in files.items():
        a = by_file[str(path)]
        k = int(np.flatnonzero(fit.track_id == tid)[0])
        rows = np.flatnonzero(fit.span[:, k])
        assert a["frame_range"] == [1, len(rows)], "frame count"
        assert a["fps"] == pytest.approx(fit.fps, rel=1e-3), "frame rate"
        H = np.array([[fr[n] for n in fit.joint_names] for fr in a["heads"]])  # Blender z up = world
        err = np.linalg.norm(H - P[rows, k], axis=-1)
        worst_head = max(worst_head, float(err.max()))
        for j, p in enumerate(fit.parents):
            if p >= 0:
                d = np.linalg.norm(H[:, j] - H[:, p], axis=-1)
                worst_len = max(worst_len, float(np.ptp(d)))
    assert worst_head < 0.01, f"bone heads {1000 * worst_head:.2f} mm from the fitted joints (limit 10 mm)"
    assert worst_len < 0.001, f"bone lengths vary by {1000 * worst_len:.3f} mm (limit 1 mm)"
    return {"head_err_max_m": worst_head, "bone_length_ptp_max_m": worst_len}


def test_blender_imports_one_armature_per_person(tmp_path):
    from tests.test_outputs_export import _trackfile, _walkers

    xyz = _walkers(2, 40) + np.random.default_rng(1).normal(0, 0.005, (40, 2, 19, 3))
    xyz[:8, 1] = np.nan  # the second person enters later: its file starts there
    fit = fit_skeletons(_trackfile(xyz))
    files = {}
    for tid in fit.track_id.tolist():
        files[tid] = tmp_path / f"S_{tid}.bvh"
        write_bvh(fit, files[tid], track_ids=[tid])
    got = blender_import(list(files.values()), tmp_path / "probe.json")
    check_armatures(fit, files, got)


def test_blender_imports_finger_bones(tmp_path):
    """A whole-body track (body19 and both hands, fingers curling): the BVH's finger bones hang off the
    wrists, 4 per finger from the hand root, and Blender's armature has them at the fitted positions and
    lengths; the right hand is unseen for a stretch (held, not dropped). A second person whose right hand
    is never seen imports too (that hand's bones collapsed on the wrist)."""
    from hands_helpers import SK, wholebody_trackfile, wholebody_xyz

    from roomcap.keypoints.skeletons import FINGERS, HANDS

    xyz = wholebody_xyz(2, 30) + np.random.default_rng(2).normal(0, 0.002, (30, 2, SK.n_joints, 3))
    right = [SK.index(n) for n in HANDS[21:]]
    xyz[12:26, 0, right] = np.nan  # longer than the fit's gap filling
    xyz[:, 1, right] = np.nan  # never seen
    fit = fit_skeletons(wholebody_trackfile(xyz))
    files = {tid: tmp_path / f"S_{tid}.bvh" for tid in (3, 4)}
    for tid, path in files.items():
        write_bvh(fit, path, track_ids=[tid])
    got = blender_import(list(files.values()), tmp_path / "probe.json")
    stats = check_armatures(fit, files, got)
    assert np.isnan(fit.finger_lengths_m(1)["right_thumb"]).all()
    path = files[3]
    a = next(x for x in got["armatures"] if x["file"] == str(path))
    par = a["parents"]
    for side in ("left", "right"):
        assert par[f"{side}_hand_root"] == f"{side}_wrist"
        for f in FINGERS:
            chain = [f"{side}_{f}{i}" for i in range(1, 5)]
            assert par[chain[0]] == f"{side}_hand_root"
            assert [par[c] for c in chain[1:]] == chain[:-1], chain
    # a finger bone in Blender spans its joint to the next one: its length is the fit's next bone
    names = list(fit.joint_names)
    for side in ("left", "right"):
        for f in FINGERS:
            for i in range(1, 4):
                L = fit.bone_length_m[0, names.index(f"{side}_{f}{i + 1}")]
                assert 0.01 < L < 0.05
                got_len = np.array([fr[f"{side}_{f}{i}"] for fr in a["lengths"]])
                np.testing.assert_allclose(got_len, L, atol=2e-4, err_msg=f"{side}_{f}{i}")
    # the fingertips follow the curl: head error on the hands small where the hand was seen
    P = np.array([[fr[n] for n in HANDS] for fr in a["heads"]])
    seen = np.isfinite(xyz[:, 0, [SK.index(n) for n in HANDS]]).all(-1)
    err = np.linalg.norm(P - xyz[:, 0, [SK.index(n) for n in HANDS]], axis=-1)[seen]
    print(f"finger heads: median {1e3 * np.median(err):.1f} mm, max {1e3 * err.max():.1f} mm from the track; "
          f"heads {1e3 * stats['head_err_max_m']:.2f} mm from the fit")  # fmt: skip
    assert np.median(err) < 0.006 and err.max() < 0.03, (np.median(err), err.max())
    assert np.isfinite(P[:, 21:]).all()  # the unseen right hand is held, not dropped
