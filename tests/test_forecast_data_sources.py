"""The data sources of the retraining: every one-person CMU clip (``clips.load_one_person_all``, split by
clip, the 8-action benchmark's test files test only) and the real two-person takes
(``clips.load_two_person_real``, split by take). Need the shared motion data; skipped without it."""

from __future__ import annotations

import pytest

from roomcap.forecast.lab import clips as C
from roomcap.forecast.lab import data as D


def _or_skip(fn):
    try:
        return fn()
    except FileNotFoundError as e:
        pytest.skip(f"shared motion data not available: {e}")


@pytest.mark.slow
def test_one_person_all_split_by_clip_benchmark_test_files_test_only():
    d = _or_skip(C.load_one_person_all)
    names = [[c.name for c in part] for part in (d.train, d.val, d.test)]
    tr, va, te = (set(n) for n in names)
    assert len(tr) + len(va) + len(te) == sum(len(n) for n in names)  # no clip in two parts
    assert not (tr & va or tr & te or va & te)
    assert {n for n in te if n.startswith("cmu8_")} == {n for n in tr | va | te if n.startswith("cmu8_test_")}
    assert any(n.startswith("cmu8_train_") for n in tr) and not any(n.startswith("cmu8_") for n in va)
    assert all(c.xyz_m.shape[1] == 1 for c in d.clips)  # one person each: no salsa pair, no 18_01 + 19_01
    old_tr, old_va, old_te = C.split_clips(C.load_cmu(), 0)
    assert {c.name for c in old_te} <= te and {c.name for c in old_tr} <= tr  # the CMU split is kept
    assert d.activities["cmu8_test_walking_1"] == "cmu8 walking" and "cmu8_test_walking_1" in te
    assert d.activities["08_01"] != D.UNLABELLED  # cmu-more clips carry their manifest activity
    assert sum(c.n_frames for c in d.train) / d.train[0].fps / 60 > 15  # minutes of training motion


def test_two_person_real_split_by_take():
    d = _or_skip(C.load_two_person_real)
    assert all(c.xyz_m.shape[1] == 2 for c in d.clips)
    held = {c.name for c in d.test}
    assert len(held) == 3 and not held & {c.name for c in d.train + d.val}
    assert "18_01+19_01" in {c.name for c in d.train}
    assert {d.activities[c.name] for c in d.test} == {"salsa dance"}
