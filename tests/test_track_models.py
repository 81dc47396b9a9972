"""Normalisation (eq. 5.2-5.5), motion priors (eq. 5.1) and the track package's import boundary."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from roomcap.keypoints.skeletons import CANONICAL, get_skeleton
from roomcap.track.normalize import denormalize, hip_frame, normalize
from roomcap.track.priors import ConstantVelocityPrior, ZeroVelocityPrior, gather_state

PEL, LH, RH = CANONICAL.index("pelvis"), CANONICAL.index("left_hip"), CANONICAL.index("right_hip")


def test_normalize_hips_on_x_and_round_trip(rng):
    x = rng.normal(0, 0.3, (50, 19, 3)).astype(np.float32) + rng.uniform(-3, 3, (50, 1, 3)).astype(np.float32)
    x[:, PEL] = 0.5 * (x[:, LH] + x[:, RH])
    o, th = hip_frame(x)
    xh = normalize(x, o, th)
    assert np.abs(xh[:, PEL]).max() < 1e-5  # hip centre at the origin
    d = xh[:, RH] - xh[:, LH]
    assert np.abs(d[:, 1]).max() < 1e-5 and (d[:, 0] > 0).all()  # left -> right hip along +x
    assert np.allclose(xh[..., 2], x[..., 2] - o[:, None, 2], atol=1e-5)  # z untouched (rotation about z)
    assert np.abs(denormalize(xh, o, th) - x).max() < 1e-5


def test_priors_shapes_and_motion(rng):
    x0 = rng.normal(0, 0.3, (10, 19, 3)).astype(np.float32)
    x1 = x0 + np.float32([0.04, 0, 0])
    cv = ConstantVelocityPrior(sigma_m=0.0, damping=1.0)
    st = cv.init_state(x0)
    _, st = cv.predict(x0, st, rng)
    x2, st = cv.predict(x1, st, rng)
    assert np.allclose(x2 - x1, [0.04, 0, 0], atol=1e-6)  # constant velocity continues
    zv = ZeroVelocityPrior(sigma_m=0.01)
    y, _ = zv.predict(x1, {}, rng)
    assert 0.007 < float(np.std(y - x1)) < 0.013
    st2 = gather_state(st, np.array([3, 3, 1]))
    assert st2["prev"].shape == (3, 19, 3) and np.array_equal(st2["prev"][0], st["prev"][3])
    with pytest.raises(ValueError, match=r"\(B,19,3\)"):
        zv.predict(x1[:, :5], {}, rng)


def test_non_learned_track_imports_without_torch():
    code = (
        "import sys; import track.particle, track.observation, track.normalize, track.priors, "
        "track.stage; print('torch' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_gru_prior_dropout_diversity_and_checkpoint_mismatch(tmp_path, rng):
    torch = pytest.importorskip("torch")
    from roomcap.track.motion import (
        DEFAULT_CHECKPOINT,
        CheckpointMismatch,
        GRUPrior,
        PoseGRU,
        save_checkpoint,
    )

    torch.set_num_threads(1)
    assert DEFAULT_CHECKPOINT.exists() and DEFAULT_CHECKPOINT.stat().st_size < 2_000_000
    x = np.repeat(rng.normal(0, 0.3, (1, 19, 3)).astype(np.float32), 64, 0)
    on = GRUPrior.load(fps=25.0)
    off = GRUPrior.load(fps=25.0, dropout=0.0)
    y_on, st = on.predict(x, on.init_state(x), rng)
    y_off, _ = off.predict(x, off.init_state(x), rng)
    assert y_on.shape == x.shape and st["h"].shape == (64, on.model.hidden)
    assert float(y_off.std(0).max()) < 1e-6  # no dropout: identical inputs give identical forecasts
    assert float(y_on.std(0).mean()) > 1e-4  # dropout kept on at inference: the samples diverge
    # a checkpoint trained for another skeleton is refused with a clear message
    coco = get_skeleton("coco17")
    bad = tmp_path / "coco.pt"
    save_checkpoint(bad, PoseGRU(coco.n_joints, 8, 0.5), 25.0, coco, {})
    with pytest.raises(CheckpointMismatch, match="coco17.*17 joints.*body19.*19 joints"):
        GRUPrior.load(bad)
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointMismatch, match="not a readable motion checkpoint"):
        GRUPrior.load(tmp_path / "junk.pt")
    with pytest.raises(FileNotFoundError, match="train_motion"):
        GRUPrior.load(tmp_path / "missing.pt")


def test_trainers_write_loadable_checkpoints(tmp_path):
    """Both trainers share one loop; a few steps on the real mocap give checkpoints the tracker loads."""
    pytest.importorskip("torch")
    from conftest import need_shared

    from roomcap.track import train_birth, train_motion
    from roomcap.track.birth import BirthGenerator
    from roomcap.track.motion import GRUPrior

    mocap = need_shared("data", "motion")
    clips = [np.zeros((10, 19, 3), np.float32) + i for i in range(3)]
    train, val = train_motion.split_clips(clips, ["a_01", "b_02", "c_11"], "1")
    assert [int(c[0, 0, 0]) for c in train] == [1] and [int(c[0, 0, 0]) for c in val] == [0, 2]
    train_motion.main(
        ["--out", str(tmp_path / "m.pt"), "--steps", "3", "--hidden", "8", "--mocap", str(mocap)]
    )
    train_birth.main(
        ["--out", str(tmp_path / "b.pt"), "--steps", "3", "--hidden", "16", "--mocap", str(mocap)]
    )
    assert GRUPrior.load(tmp_path / "m.pt", fps=25.0).model.hidden == 8
    assert BirthGenerator.load(tmp_path / "b.pt") is not None
