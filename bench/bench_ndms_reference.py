"""NDMS per word against the seed's reference search: the project's scorer (exact nearest neighbour over the
seed's root-centred words) and the reference code's way of finding the neighbour (jutanke/ndms: an Annoy
index, Euclidean, 10 trees, on float32 flattened words), both scored by eq. 6.11/6.12 (``metrics.ndms_pair``,
checked against the reference rule on a hand-computed fixture in tests/test_forecast_ndms_reference.py).

100 windows of held-out CMU motion (the old CMU test split, as the evaluation), 0.3 s observed + 1 s of
constant-velocity forecast, D = the held-out clips of the window's activity (own clip included).

    OPENBLAS_NUM_THREADS=1 python bench/bench_ndms_reference.py

Needs the CMU BVH and ``annoy`` (extra ``bench``). Ends with one line ``BENCH {json}``.
"""

from __future__ import annotations

import json
import time

import numpy as np

from roomcap.forecast.lab import data as D
from roomcap.forecast.lab import evaluate as E
from roomcap.forecast.lab import metrics as M
from roomcap.forecast.lab.clips import clip_activities, load_cmu, split_clips

N_WINDOWS, N_OBS, N_FUT, KAPPA = 100, 8, 25, 8


def main() -> None:
    from annoy import AnnoyIndex

    te = split_clips(load_cmu(), 0)[2]
    acts = clip_activities(te)
    sc = E.ndms_scorer_for(te, activities=acts)
    ws = D.make_windows(te, N_OBS, N_FUT, stride=7, persons="each")
    sel = np.sort(np.random.default_rng(0).choice(len(ws), min(N_WINDOWS, len(ws)), replace=False))
    indexes: dict[str, tuple] = {}
    t0 = time.perf_counter()
    for a in sc.activities:
        ids = np.flatnonzero(sc.activity_of_word == a)
        ix = AnnoyIndex(sc.flat.shape[1], "euclidean")
        for k, i in enumerate(ids):
            ix.add_item(k, sc.flat[i].astype(np.float32))
        ix.build(10)
        indexes[a] = (ix, ids)
    t_build = time.perf_counter() - t0
    diffs, win_diffs, same_nn = [], [], []
    for i in sel:
        obs = ws.x[i, :N_OBS, 0].astype(np.float64)
        fut = obs[-1] + (obs[-1] - obs[-2]) * np.arange(1, N_FUT + 1)[:, None, None]
        seq = np.concatenate([obs[-(KAPPA - 1) :], fut], 0)
        a = acts[te[ws.clip[i]].name]
        ours = sc.word_scores(seq, activity=a)
        q = M.motion_words(np.asarray(np.asarray(seq, np.float32), np.float64), KAPPA, sc.lhip, sc.rhip)[
            :, :, sc.jsel
        ]
        ix, ids = indexes[a]
        exact = []
        theirs = []
        for w in q:
            flat = w.reshape(-1)
            k = ix.get_nns_by_vector(flat.astype(np.float32), 1)[0]
            theirs.append(float(M.ndms_pair(w, sc.words[ids[k]])))
            d = ((sc.flat[ids] - flat) ** 2).sum(1)
            exact.append(int(ids[np.argmin(d)]) == int(ids[k]))
        theirs_a = np.array(theirs)
        diffs.append(np.abs(ours - theirs_a))
        win_diffs.append(abs(float(ours.mean() - theirs_a.mean())))
        same_nn.append(np.mean(exact))
    dw = np.concatenate(diffs)
    print(f"{len(sel)} windows, {len(dw)} words; D: {len(sc.words)} words in {len(sc.activities)} activities")
    print(
        f"per word |ours - reference search|: mean {dw.mean():.2e}, 95 % {np.percentile(dw, 95):.2e}, "
        f"max {dw.max():.3f}; words within 0.01: {np.mean(dw <= 0.01):.3f}; "
        f"same neighbour: {np.mean(same_nn):.3f}"
    )
    print(f"per window mean score: max |diff| {max(win_diffs):.4f}, mean {np.mean(win_diffs):.2e}")
    bench = {
        "n_windows": len(sel),
        "n_words": len(dw),
        "word_abs_diff_mean": float(dw.mean()),
        "word_abs_diff_max": float(dw.max()),
        "words_within_0_01": float(np.mean(dw <= 0.01)),
        "same_neighbour": float(np.mean(same_nn)),
        "window_abs_diff_max": float(max(win_diffs)),
        "annoy_build_s": t_build,
    }
    print("BENCH " + json.dumps(bench))


if __name__ == "__main__":
    main()
