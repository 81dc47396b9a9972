"""NDMS against the seed's published implementation (jutanke/ndms, MIT), restated here as that code works:
every window of κ frames of every database sequence, cast to float32 and transformed (here: every frame's pose
minus its own root, heading kept, as Tables 6.3/6.8 score), flattened; a query word is transformed the same
way, its nearest database word found by Euclidean distance on the flattened words (the reference uses an
approximate Annoy index; the restatement searches exhaustively), and the two scored per frame step and joint
with velocity norms clamped at ε = 1e-7: ψ = ½ (1 + a·b / (max(|a|,ε) max(|b|,ε))) · min(…)/max(…).

A fixture with values computed by hand checks both to 1e-6; 100 real CMU windows check that the project's
scorer (vectorised, exhaustive search) gives the restatement's per-word scores."""

from __future__ import annotations

import math

import numpy as np
import pytest

from roomcap.forecast.lab import data as D
from roomcap.forecast.lab import metrics as M

EPS = 1e-7


def _psi_loop(true_word: np.ndarray, query_word: np.ndarray) -> float:
    """The reference's per-word score, one frame step and one joint at a time. Words (κ,J,3)."""
    vt = np.diff(np.asarray(true_word, np.float32), axis=0)  # the reference's velocities are float32
    vq = np.diff(np.asarray(query_word, np.float32), axis=0)
    k1, J = vt.shape[:2]
    total = 0.0
    for t in range(k1):
        for j in range(J):
            a, b = vt[t, j].astype(np.float64), vq[t, j].astype(np.float64)
            na, nb = max(float(np.linalg.norm(a)), EPS), max(float(np.linalg.norm(b)), EPS)
            cos = float(a @ b) / (na * nb)
            total += 0.5 * (1.0 + cos) * (min(na, nb) / max(na, nb)) / J
    return total / k1


def _root_centred_words(seq: np.ndarray, kappa: int, lhip: int, rhip: int, jsel: np.ndarray) -> np.ndarray:
    out = []
    for f in range(len(seq) - kappa + 1):
        w = np.asarray(seq[f : f + kappa], np.float32).astype(np.float64)
        w = w - 0.5 * (w[:, lhip : lhip + 1] + w[:, rhip : rhip + 1])
        out.append(w[:, jsel])
    return np.stack(out)


class ReferenceDatabase:
    """The reference's database and rolling query, with an exhaustive nearest-neighbour search."""

    def __init__(self, database, names, kappa=8):
        self.kappa = kappa
        self.lhip, self.rhip = D.hip_indices(names)
        self.jsel = np.array([list(names).index(n) for n in M.NDMS_JOINTS if n in names])
        self.words = np.concatenate([self._words(s) for s in database])
        self.flat = self.words.reshape(len(self.words), -1)

    def _words(self, seq):
        return _root_centred_words(seq, self.kappa, self.lhip, self.rhip, self.jsel)

    def scores(self, query):
        """Per-word scores of query (T,J,3)."""
        out = []
        for q in self._words(query):
            nn = int(np.argmin(((self.flat - q.reshape(1, -1)) ** 2).sum(1)))
            out.append(_psi_loop(self.words[nn], q))
        return np.array(out)


def reference_scores(database, query, names, kappa=8):
    return ReferenceDatabase(database, names, kappa).scores(query)


# ----------------------------------------------------------------------------- per-word score, by hand


def test_word_score_by_hand_matches_the_reference_rule():
    """κ = 3, two joints; velocities (frame steps) chosen so that every ψ is known in closed form."""
    v_true = np.array(
        [
            [[1.0, 0, 0], [0, 0, 0]],  # step 1: joint 0 moves +x by 1; joint 1 still
            [[0, 1.0, 0], [0, 0, 0]],  # step 2: joint 0 moves +y by 1; joint 1 still
        ]
    )
    v_query = np.array(
        [
            [
                [2.0, 0, 0],
                [0, 0, 0],
            ],  # same direction, twice as fast -> ψ = ½(1+1)·(1/2) = 0.5; still/still -> ½
            [[0, -1.0, 0], [0, 0, 3e-8]],  # opposite -> ψ = 0; 3e-8 < ε and 0: both clamped, cos 0 -> ψ = ½
        ]
    )
    x = np.concatenate([np.zeros((1, 2, 3)), np.cumsum(v_true, 0)])
    y = np.concatenate([np.zeros((1, 2, 3)), np.cumsum(v_query, 0)])
    # eq. 6.11: mean over the κ-1 = 2 steps of the mean over J = 2 joints: ((0.5 + 0.5)/2 + (0 + 0.5)/2) / 2
    hand = ((0.5 + 0.5) / 2 + (0.0 + 0.5) / 2) / 2
    assert hand == 0.375
    assert float(M.ndms_pair(x, y)) == pytest.approx(hand, abs=1e-6)
    assert _psi_loop(x, y) == pytest.approx(hand, abs=1e-6)
    # 45°, magnitudes 1 and √2: ψ = ½ (1 + 1/√2) · (1/√2) = (√2 + 1) / 4, for a single moving joint
    a = np.array([[[0, 0, 0]], [[1.0, 0, 0]]])
    b = np.array([[[0, 0, 0]], [[1.0, 1.0, 0]]])
    hand45 = (math.sqrt(2) + 1) / 4
    assert float(M.ndms_pair(a, b)) == pytest.approx(hand45, abs=1e-6)
    assert _psi_loop(a, b) == pytest.approx(hand45, abs=1e-6)
    assert float(M.ndms_pair(b, a)) == pytest.approx(hand45, abs=1e-6)  # symmetric


# ----------------------------------------------------------------------------- search + score, by hand

NAMES3 = (
    "left_hip",
    "right_hip",
    "left_wrist",
)  # scored in NDMS_JOINTS order: left_wrist, left_hip, right_hip
HIPS = np.array([[-0.1, 0, 0], [0.1, 0, 0]])  # root-centred hips, still relative to the root


def _world(wrist_rc: list, root: list) -> np.ndarray:
    """Frames of (left_hip, right_hip, left_wrist) from the root-centred wrist and the root (mid-hips)."""
    return np.array([np.vstack([HIPS, [w]]) + np.array(r) for w, r in zip(wrist_rc, root, strict=True)])


def test_search_and_score_by_hand():
    """κ = 2: one word per two-frame sequence. Root-centred wrist positions (r) and roots (w):

    D1: wrist r (0, .2, -.2) -> (0, .3, -.2), the root walks 1 m along x (ignored by the seed's words)
    D2: wrist r (0, -.2, -.2) -> (0, -.2, -.4), the root stands at (5, 5, 1)
    Q:  wrist r (0, .25, -.2) -> (0, .35, -.1), the root walks 2 m along y

    Squared distances of the root-centred words (only the wrist differs): Q-D1 = .05² + (.05² + .1²) = .015;
    Q-D2 = .45² + (.55² + .3²) = .595 -> NN = D1. Wrist velocities: D1 (0, .1, 0), Q (0, .1, .1): cos = 1/√2,
    magnitudes .1 and .1√2 -> ψ = (√2 + 1)/4; the hips are still relative to the root in both: ψ = ½ each
    (the clamp). NDMS = ((√2 + 1)/4 + ½ + ½) / 3."""
    d1 = _world([(0, 0.2, -0.2), (0, 0.3, -0.2)], [(0, 0, 1), (1, 0, 1)])
    d2 = _world([(0, -0.2, -0.2), (0, -0.2, -0.4)], [(5, 5, 1), (5, 5, 1)])
    q = _world([(0, 0.25, -0.2), (0, 0.35, -0.1)], [(0, 0, 1), (0, 2, 1)])
    hand = ((math.sqrt(2) + 1) / 4 + 0.5 + 0.5) / 3
    sc = M.NDMSScorer([d1, d2], NAMES3, kappa=2, min_words=1)
    ours = sc.word_scores(q)
    ref = reference_scores([d1, d2], q, NAMES3, kappa=2)
    assert ours.shape == (1,) and ref.shape == (1,)
    assert abs(float(ours[0]) - hand) <= 1e-6 and abs(float(ref[0]) - hand) <= 1e-6
    # the same pose frozen and slid 2 m along y: no joint moves relative to the root -> only the clamped
    # still/still hips score (½ each of the 3 joints; the wrist, moving in D1, scores 0)
    slid = _world([(0, 0.25, -0.2), (0, 0.25, -0.2)], [(0, 0, 1), (0, 2, 1)])
    assert abs(float(sc.word_scores(slid)[0]) - 1 / 3) <= 1e-6
    assert abs(float(reference_scores([d1, d2], slid, NAMES3, kappa=2)[0]) - 1 / 3) <= 1e-6
    # the first-frame variant keeps the root's motion inside the word: all three joints of the slid pose move
    w = M.motion_words_first_frame(slid, 2, 0, 1)  # (1,2,J,3), heading of frame 1 already along +x
    assert np.allclose(w[0, 1] - w[0, 0], [0, 2, 0])
    assert np.allclose(M.motion_words(slid, 2, 0, 1)[0, 1] - M.motion_words(slid, 2, 0, 1)[0, 0], 0)
    with pytest.raises(ValueError, match="word form"):
        M.NDMSScorer([d1, d2], NAMES3, kappa=2, min_words=1, word_form="pelvis")


# ----------------------------------------------------------------------------- 100 real windows


N_FUT = 12  # forecast frames per window: 12 words each, 1,200 words in all


def _cmu_clips_or_skip():
    from roomcap.forecast.lab.clips import load_cmu
    from roomcap.synthetic import bvh

    root = bvh.mocap_root()
    folder = None if root is None else root / "cmu-bvh-subjects01-07"
    if folder is None or not folder.is_dir():
        pytest.skip("CMU BVH (cmu-bvh-subjects01-07) not available under the mocap root")
    return load_cmu(root=folder)[::6]


@pytest.mark.slow
def test_real_windows_agree_with_the_reference_after_the_search():
    """100 windows of real CMU motion (0.3 s observed, 0.5 s of constant-velocity forecast) scored against a
    database of the same clips: every word's score from the project's scorer equals the restatement's."""
    from roomcap.keypoints.skeletons import get_skeleton

    clips = _cmu_clips_or_skip()
    names = get_skeleton("body19").joint_names
    db = [c.xyz_m[:, 0] for c in clips if np.isfinite(c.xyz_m).all()]
    sc = M.NDMSScorer(db, names, kappa=8)
    ref = ReferenceDatabase(db, names, kappa=8)
    ws = D.make_windows(clips, 8, N_FUT, stride=5, persons="each")
    sel = np.random.default_rng(0).choice(len(ws), min(100, len(ws)), replace=False)
    worst, n_words = 0.0, 0
    for i in sel:
        obs = ws.x[i, :8, 0].astype(np.float64)
        fut = obs[-1] + (obs[-1] - obs[-2]) * np.arange(1, N_FUT + 1)[:, None, None]  # constant velocity
        seq = np.concatenate([obs[-7:], fut], 0)
        ours, theirs = sc.word_scores(seq), ref.scores(seq)
        n_words += len(ours)
        worst = max(worst, float(np.abs(ours - theirs).max()))
    assert len(sel) == 100 and n_words == 100 * N_FUT
    assert worst <= 0.01  # measured below 1e-6: the same nearest neighbour, the same per-word score
