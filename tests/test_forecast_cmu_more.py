"""Readers of cmu-more: the cgspeed BVH at its known scale, the salsa pair as one two-person clip, the CMU
8-action benchmark's exp-map through the CMU ASF forward kinematics; bone lengths against the other CMU
readers."""

from __future__ import annotations

import numpy as np
import pytest

from roomcap.core.errors import FormatError, InputError
from roomcap.forecast.lab import cmu_more as C
from roomcap.synthetic import bvh
from tests.conftest import need_shared

J = {n: i for i, n in enumerate(bvh.BODY19)}


def _bones(x: np.ndarray) -> dict[str, float]:
    """Median left leg (hip-knee-ankle) and arm (shoulder-elbow-wrist) of body19 (T,19,3) or (T,P,19,3)."""
    x = x.reshape(-1, 19, 3)

    def d(a, b):
        return float(np.nanmedian(np.linalg.norm(x[:, J[a]] - x[:, J[b]], axis=-1)))

    return {
        "leg": d("left_hip", "left_knee") + d("left_knee", "left_ankle"),
        "arm": d("left_shoulder", "left_elbow") + d("left_elbow", "left_wrist"),
        "thigh": d("left_hip", "left_knee"),
        "shin": d("left_knee", "left_ankle"),
    }


@pytest.fixture(scope="module")
def cmu_asf_bones() -> list[dict[str, float]]:
    """Bones of two subjects through the CMU ASF unit (01_01 of cmu-bvh-01, 18_01 of the two-person take)."""
    f1 = need_shared("data", "motion", "cmu-bvh-01", "01_01.bvh")
    f2 = need_shared("data", "motion", "cmu-two-person-18-19", "18_01.bvh")
    return [_bones(bvh.load_clip(f).xyz_m) for f in (f1, f2)]


def test_cgspeed_scale_known_and_tpose_dropped(cmu_asf_bones):
    single = need_shared("data", "motion", "cmu-more", "single", "08", "08_01.bvh")
    salsa = need_shared("data", "motion", "cmu-more", "two-person", "salsa_10", "60_10.bvh")
    a, b = bvh.load_clip(single), bvh.load_clip(salsa)
    assert a.unit == "cm" and b.unit == "cgspeed/128"
    # frame 0 (the T-pose) is always dropped for the cgspeed skeleton
    assert a.n_frames == bvh.read_bvh(single).n_frames - 1
    assert b.n_frames == bvh.read_bvh(salsa).n_frames - 1
    ba, bb = _bones(a.xyz_m), _bones(b.xyz_m)
    for k in ("thigh", "shin", "arm"):  # one skeleton at two writings: the same bones in metres
        assert abs(ba[k] - bb[k]) < 0.002, (k, ba[k], bb[k])
    for ref in cmu_asf_bones:  # against CMU's ASF unit: legs within 5 %, arms within 12 % (the rig's wrist)
        assert abs(ba["leg"] / ref["leg"] - 1) < 0.05, (ba, ref)
        assert abs(ba["arm"] / ref["arm"] - 1) < 0.12, (ba, ref)
    # standing height (nose above the floor) of an adult
    assert 1.35 < float(np.nanpercentile(a.xyz_m[:, J["nose"], 2], 90)) < 1.85


def test_benchmark_fk_bones_match_cmu_readers(cmu_asf_bones):
    f = need_shared("data", "motion", "cmu-more", "benchmark-cmu8", "test", "running", "running_1.txt")
    ex = C.read_expmap(f)
    xyz = C.expmap_to_xyz(ex)
    assert xyz.shape == (len(ex), 38, 3)
    # the root's position and rotation never enter (the reference's body frame): the hips are fixed
    assert np.allclose(xyz[:, 2], C.CMU38_OFFSETS[2]) and np.allclose(xyz[:, 0], 0)
    # bone lengths are kept by the forward kinematics
    assert np.allclose(np.linalg.norm(xyz[:, 3] - xyz[:, 2], axis=-1), np.linalg.norm(C.CMU38_OFFSETS[3]))
    clip = C.benchmark_clip(f)
    assert clip.fps == C.BENCHMARK_FPS and clip.xyz_m.shape == (len(ex), 1, 19, 3)
    bb = _bones(clip.xyz_m)
    for ref in cmu_asf_bones:
        assert abs(bb["leg"] / ref["leg"] - 1) < 0.05, (bb, ref)
        assert abs(bb["arm"] / ref["arm"] - 1) < 0.12, (bb, ref)
    x = clip.xyz_m[:, 0]  # z up, nose in front of the neck (forward = left x up)
    assert np.median(x[:, J["neck"], 2] - x[:, J["left_ankle"], 2]) > 1.0
    left = x[:, J["left_hip"]] - x[:, J["right_hip"]]
    fwd = np.cross(left, [0.0, 0.0, 1.0])
    assert np.median(np.sum((x[:, J["nose"]] - x[:, J["neck"]]) * fwd, -1)) > 0


def test_expmap_zero_pose_is_the_offsets():
    xyz = C.expmap_to_xyz(np.zeros((2, 117)))
    exp = np.zeros((38, 3))
    for i in range(38):  # rest pose: sum of the offsets along the chain
        j = i
        while j > 0:
            exp[i] += C.CMU38_OFFSETS[j]
            j = int(C.CMU38_PARENTS[j])
    assert np.allclose(xyz[0], exp) and np.allclose(xyz[1], exp)


def test_salsa_pair_is_one_two_person_clip():
    folder = need_shared("data", "motion", "cmu-more", "two-person", "salsa_10")
    c = C.salsa_clip(folder, fps=None)
    n = bvh.read_bvh(folder / "60_10.bvh").n_frames
    assert c.name == "60_10+61_10" and c.xyz_m.shape == (n - 1 - C.SALSA_BLEND_FRAMES, 2, 19, 3)
    assert c.fps == pytest.approx(30.0, abs=1e-3)
    # one world frame: the partners dance within arm's reach, never on top of each other
    d = np.linalg.norm(c.xyz_m[:, 0, J["pelvis"], :2] - c.xyz_m[:, 1, J["pelvis"], :2], axis=-1)
    assert 0.2 < float(np.median(d)) < 2.0
    # the blend out of the T-pose is gone: the first steps are like the take's typical step (mean over joints)
    step = np.linalg.norm(np.diff(c.xyz_m, axis=0), axis=-1).mean(-1)
    assert step[:3].max() < 3 * np.median(step), (step[:3], np.median(step, 0))


def test_salsa_pair_frame_counts_differ(tmp_path):
    folder = need_shared("data", "motion", "cmu-more", "two-person", "salsa_10")
    take = tmp_path / "salsa_10"
    take.mkdir()
    (take / "60_10.bvh").write_bytes((folder / "60_10.bvh").read_bytes())
    head, _, motion = (folder / "61_10.bvh").read_text().partition("MOTION")
    lines = motion.strip().splitlines()
    short = ["Frames: 100", lines[1]] + lines[2:102]
    (take / "61_10.bvh").write_text(head + "MOTION\n" + "\n".join(short) + "\n")
    with pytest.raises(InputError, match=r"61_10.bvh has 99 .*same frame count"):
        C.salsa_clip(take)
    (take / "61_10.bvh").unlink()
    with pytest.raises(InputError, match="missing"):
        C.salsa_clip(take)


def test_benchmark_missing_files_named(tmp_path):
    root = tmp_path / "benchmark-cmu8"
    (root / "train" / "walking").mkdir(parents=True)
    (root / "test" / "walking").mkdir(parents=True)
    for k in (1, 2, 4):
        (root / "train" / "walking" / f"walking_{k}.txt").write_text("0," * 116 + "0\n")
    (root / "test" / "walking" / "walking_1.txt").write_text("0," * 116 + "0\n")
    bf = C.benchmark_files(root)
    assert [p.name for p in bf.files["train"]["walking"]] == [
        "walking_1.txt",
        "walking_2.txt",
        "walking_4.txt",
    ]
    assert "train/walking/walking_3.txt" in bf.missing and "train/walking/walking_5.txt" in bf.missing
    assert "test/soccer/soccer_1.txt" in bf.missing and "test/walking/walking_1.txt" not in bf.missing
    with pytest.raises(InputError, match="no train/ or test/"):
        C.benchmark_files(tmp_path / "nothing")
    bad = tmp_path / "bad.txt"
    bad.write_text("1,2,3\n")
    with pytest.raises(FormatError, match="expected 117"):
        C.read_expmap(bad)


def test_shared_benchmark_names_the_missing_test_files():
    need_shared("data", "motion", "cmu-more", "benchmark-cmu8", "test")
    bf = C.benchmark_files()
    assert "test/basketball_signal/basketball_signal_1.txt" in bf.missing
    assert "test/directing_traffic/directing_traffic_1.txt" in bf.missing
    assert bf.files["test"]["walking"] and not bf.files["train"]["washwindow"]
