"""Two people over a long horizon (forecast.pairs): the partners' distance and facing angle, their range
against the real takes, NDMS per person and SSCP, on toy takes of two people facing each other."""

from __future__ import annotations

import numpy as np
import pytest

from roomcap.forecast.lab import data as D
from roomcap.forecast.lab import evaluate as E
from roomcap.forecast.lab import pairs
from roomcap.forecast.lab import train as T
from roomcap.forecast.lab.protocol import render
from roomcap.forecast.lab.toy import walker
from roomcap.keypoints.skeletons import get_skeleton

LH, RH = D.hip_indices(get_skeleton("body19").joint_names)


def _take(name, n=200, gap=1.2, phase=0.0, sway=0.15):
    a = walker(n, speed_mps=0.0, heading_rad=0.0, phase=phase, sway_rad=sway)  # faces +y
    b = walker(n, speed_mps=0.0, heading_rad=np.pi, start=(0.0, gap), phase=phase + 1, sway_rad=sway)  # -y
    return D.Clip(name, np.stack([a, b], 1), 25.0)


def test_distance_and_facing_of_a_pair():
    X = _take("t", 10, sway=0.0).xyz_m  # hips square to the partner (sway turns them)
    assert pairs.partner_distance(X, LH, RH) == pytest.approx(np.full(10, 1.2), abs=1e-5)
    assert pairs.facing_angle(X, LH, RH) == pytest.approx(np.zeros(10), abs=0.1)  # face to face
    back = X.copy()
    back[:, 1] = walker(10, speed_mps=0.0, heading_rad=0.0, start=(0.0, 1.2))  # b turns away: a 0°, b 180°
    assert pairs.facing_angle(back, LH, RH) == pytest.approx(np.full(10, 90.0), abs=0.1)


def test_pairs_real_in_range_and_const_drifts_out():
    takes = [_take(f"t{i}", 200, gap=1.0 + 0.2 * i, phase=i) for i in range(3)]
    models = {"real": E.Real(), "zero": T.baseline("zero"), "const": T.baseline("const")}
    res = pairs.evaluate_pairs(
        models, takes, n_obs=25, n_pred=100, stride=40, activities={t.name: "dance" for t in takes}
    )
    r = res["models"]
    lo, hi = res["real_range"]["distance_m_5_95"]
    assert 0.95 < lo < hi < 1.45  # the three takes' gaps 1.0 / 1.2 / 1.4 m
    assert r["real"]["distance_in_range"] == 1.0 and r["real"]["sscp_jsd"] == pytest.approx(0.0, abs=1e-9)
    assert min(r["real"]["ndms"]) > 0.999  # the own take is in D: the real future scores 1
    assert (
        r["zero"]["distance_in_range"] == 1.0 and max(r["zero"]["ndms"][8:]) < 1e-3
    )  # still: in place, no motion
    assert r["real"]["ndms_p0"] == pytest.approx(r["real"]["ndms_p1"])
    assert set(r["real"]["ndms_at"]) == {"2", "4"} and len(r["const"]["distance"]) == 100
    assert "distance in range" in render(res) and "MPJPE 400 ms" in render(res) and res["protocol"] == "pairs"
    # the own take left out of D: the real future is no longer a perfect match, but still scores
    assert r["real"]["n_windows_loo"] == res["n_windows"] and 0.2 < r["real"]["ndms_loo_at"]["2"] < 0.999
    assert r["real"]["mpjpe"][9] == 0 and r["zero"]["mpjpe_best_of_k"] == pytest.approx(r["zero"]["mpjpe"])
    assert r["zero"]["mpjpe"][9] > 0.01  # the walkers move
