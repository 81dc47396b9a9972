"""The GRU motion prior from the numpy copy of its checkpoint (track.priors.load_gru_numpy): the same
forecasts as the torch-loaded prior bit for bit, a stale or foreign copy ignored, tracking without torch."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from roomcap.keypoints.skeletons import get_skeleton
from roomcap.track.priors import DEFAULT_MOTION_CHECKPOINT, load_gru_numpy, numpy_copy_path


def test_shipped_checkpoint_has_an_up_to_date_numpy_copy(rng):
    prior = load_gru_numpy(DEFAULT_MOTION_CHECKPOINT, fps=30.0, sigma_m=0.003)
    assert prior is not None, "run track.motion.write_gru_numpy_copy on the shipped checkpoint"
    torch = pytest.importorskip("torch")
    from roomcap.track.motion import GRUPrior

    torch.set_num_threads(1)
    ref = GRUPrior.load(fps=30.0, sigma_m=0.003)
    x = rng.normal(0, 0.3, (50, 19, 3)).astype(np.float32)
    state = {"prev": x - 0.01, "h": rng.normal(0, 0.3, (50, ref.hidden)).astype(np.float32)}
    a, sa = prior.predict(x, state, np.random.default_rng(3))
    b, sb = ref.predict(x, state, np.random.default_rng(3))
    assert np.array_equal(a, b) and np.array_equal(sa["h"], sb["h"])  # the same weights, the same bits
    assert prior.dropout == ref.dropout == ref.model.dropout and prior.hidden == ref.model.hidden


def test_stale_or_foreign_numpy_copy_is_ignored(tmp_path):
    pytest.importorskip("torch")
    from roomcap.track.motion import PoseGRU, save_checkpoint

    body = get_skeleton("body19")
    path = tmp_path / "m.pt"
    save_checkpoint(path, PoseGRU(body.n_joints, 8, 0.25), 25.0, body, {})
    assert numpy_copy_path(path).exists()
    prior = load_gru_numpy(path, fps=25.0)
    assert prior is not None and prior.hidden == 8 and prior.dropout == 0.25
    assert load_gru_numpy(path, fps=25.0, dropout=0.0).dropout == 0.0
    assert load_gru_numpy(path, fps=25.0, skeleton=get_skeleton("coco17")) is None  # another skeleton
    save_checkpoint(tmp_path / "other.pt", PoseGRU(body.n_joints, 4, 0.5), 25.0, body, {})
    numpy_copy_path(tmp_path / "other.pt").replace(numpy_copy_path(path))  # a copy of other bytes
    assert load_gru_numpy(path, fps=25.0) is None
    numpy_copy_path(path).write_bytes(b"junk")
    assert load_gru_numpy(path, fps=25.0) is None
    assert load_gru_numpy(tmp_path / "missing.pt", fps=25.0) is None


def test_particle_tracker_with_the_gru_prior_does_not_import_torch():
    code = (
        "import sys; import numpy as np; from track.particle import ParticleConfig, make_prior; "
        "p = make_prior(ParticleConfig(), 25.0); print(type(p).__name__, 'torch' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["GRUCellPrior", "False"]
