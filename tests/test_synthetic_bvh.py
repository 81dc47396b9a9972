"""BVH reader, forward kinematics and the body19 mapping, on the real CMU clips and on a tiny file."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import need_shared

from roomcap.keypoints.skeletons import CANONICAL
from roomcap.synthetic import bvh

J = {n: i for i, n in enumerate(CANONICAL.joint_names)}

TINY = """HIERARCHY
ROOT Hips
{
  OFFSET 0 0 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation Xrotation
  JOINT Child
  {
    OFFSET 0 10 0
    CHANNELS 3 Zrotation Xrotation Yrotation
    End Site
    {
      OFFSET 0 5 0
    }
  }
}
MOTION
Frames: 2
Frame Time: 0.5
1 2 3 0 0 0 0 0 0
0 0 0 90 0 0 0 0 0
"""


def test_tiny_fk_follows_channel_order(tmp_path):
    p = tmp_path / "tiny.bvh"
    p.write_text(TINY)
    b = bvh.read_bvh(p)
    assert b.names == ("Hips", "Child", "Child_end") and b.fps == 2.0
    assert b.channels[1] == ("Zrotation", "Xrotation", "Yrotation")
    pos, rot = b.forward_kinematics()
    np.testing.assert_allclose(pos[0], [[1, 2, 3], [1, 12, 3], [1, 17, 3]], atol=1e-12)
    # 90 deg about z maps +y to -x
    np.testing.assert_allclose(pos[1], [[0, 0, 0], [-10, 0, 0], [-15, 0, 0]], atol=1e-9)
    np.testing.assert_allclose(np.linalg.det(rot), 1.0)


def test_truncated_file_is_a_clear_error(tmp_path):
    p = tmp_path / "bad.bvh"
    p.write_text(TINY.split("MOTION")[0])
    with pytest.raises(bvh.BvhError, match="MOTION"):
        bvh.read_bvh(p)


@pytest.mark.parametrize(
    "rel",
    [
        "cmu-bvh-01/01_01.bvh",
        "cmu-bvh-131/scaled_131_02.bvh",
        "cmu-bvh-131/131_02.bvh",
        "cmu-bvh-subjects01-07/002/002_01.bvh",
    ],
)
def test_cmu_clips_to_body19(rel):
    path = need_shared("data", "motion", rel)
    x = bvh.load_bvh_body19(path, fps=25)
    assert x.shape[1:] == (19, 3) and np.isfinite(x).all()
    # bone lengths constant over time (rigid FK): std/mean < 1%   (measured <= 0.1%)
    # (limbs between BVH joints; neck/pelvis are midpoints and the face hangs off the head joint)
    rigid = [p for pairs in CANONICAL.pcp_limbs().values() for p in pairs]
    rigid += [(J["left_hip"], J["right_hip"]), (J["left_eye"], J["right_ear"]), (J["nose"], J["left_ear"])]
    for a, c in rigid:
        L = np.linalg.norm(x[:, a] - x[:, c], axis=-1)
        assert L.std() < 0.01 * L.mean(), (CANONICAL.joint_names[a], CANONICAL.joint_names[c])
    # feet near the floor: 5th percentile of the lower ankle within 0-15 cm   (measured 2-10 cm)
    ank = np.minimum(x[:, J["left_ankle"], 2], x[:, J["right_ankle"], 2])
    assert 0.0 <= np.percentile(ank, 5) < 0.15
    # height: median top of the head points 1.3-1.9 m   (measured 1.39 for 131, 1.46 for 01, 1.67 for 002)
    assert 1.3 < np.median(x[..., 2].max(1)) < 1.9
    # left is left: with forward = nose direction, the left hip lies on the person's left
    fwd = x[:, J["nose"]] - x[:, J["neck"]]
    fwd[:, 2] = 0
    left = np.cross([0.0, 0.0, 1.0], fwd)
    assert np.mean(np.sum((x[:, J["left_hip"]] - x[:, J["right_hip"]]) * left, 1) > 0) > 0.9


def test_raw_and_metre_scaled_agree():
    raw = bvh.load_clip(need_shared("data", "motion", "cmu-bvh-131", "131_02.bvh"))
    scaled = bvh.load_clip(need_shared("data", "motion", "cmu-bvh-131", "scaled_131_02.bvh"))
    assert raw.unit == "cmu" and scaled.unit == "m"
    n = min(raw.n_frames, scaled.n_frames)
    rel_r = raw.xyz_m[:n] - raw.xyz_m[:n, J["pelvis"]][:, None]
    rel_s = scaled.xyz_m[:n] - scaled.xyz_m[:n, J["pelvis"]][:, None]
    assert np.median(np.abs(rel_r - rel_s)) < 0.01  # same motion to < 1 cm


def test_resample_and_listing():
    clips = bvh.list_clips(need_shared("data", "motion"))
    assert len(clips) > 50 and not any(c.name == "131_01.bvh" for c in clips)  # raw twin left out
    c60 = bvh.load_clip(clips[-1])
    c25 = c60.resample(25)
    assert abs(c25.duration_s - c60.duration_s) < 0.1
    np.testing.assert_allclose(c25.xyz_m[0], c60.xyz_m[0])
    assert abs(bvh.clip_duration_s(clips[-1]) - c60.duration_s) < 0.05  # header only, no parsing
