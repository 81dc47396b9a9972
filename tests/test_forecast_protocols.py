"""The seed's evaluation protocols (Tanke ch. 6.3, 7.3-7.4, 8.3): NDMS database by activity with the query's
own ground truth (``ndms``) and without its clip (``ndms_loo``), root-centred DLow metrics, NPSS, the
baselines and their controls, the real two-person CMU take, the HiK protocol on a fixture, bad input."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from roomcap.core.errors import FormatError
from roomcap.core.fileio import save_npz
from roomcap.forecast.lab import data as D
from roomcap.forecast.lab import evaluate as E
from roomcap.forecast.lab import metrics as M
from roomcap.forecast.lab import train as T
from roomcap.forecast.lab.clips import clip_activities
from roomcap.forecast.lab.toy import walker
from roomcap.keypoints.skeletons import get_skeleton

NAMES = get_skeleton("body19").joint_names
SHIFT = np.array([5.0, -5.0, 0.0], np.float32)  # "moving all data by 5 m" (in the floor plane)
# Turning hips and shoulders (walker's sway_rad): NDMS words are root-centred poses, in which a rigid torso
# would be still joints (scored 1/2 by the reference's clamp, so a word would not score 1 against itself).
SWAY = 0.15


def _clips(shift=0.0):
    cs = [
        D.Clip(
            f"walk{i}",
            walker(150, phase=i, speed_mps=1.0 + 0.1 * i, heading_rad=i, sway_rad=SWAY) + shift,
            25.0,
        )
        for i in range(4)
    ]
    cs += [
        D.Clip(
            f"step{i}",
            walker(150, phase=i, speed_mps=0.05, period_s=1.5, heading_rad=-i, sway_rad=SWAY) + shift,
            25.0,
        )
        for i in range(3)
    ]
    return cs


ACTS = {**{f"walk{i}": "walk" for i in range(4)}, **{f"step{i}": "step" for i in range(3)}}


def _models():
    return {
        "real": E.Real(),
        "zero": T.baseline("zero"),
        "const": T.baseline("const"),
        "slide": T.baseline("slide"),
    }


def _run(shift=0.0):
    return E.evaluate_single(
        _models(), _clips(shift), n_obs=25, n_pred=50, n_samples=2, stride=25, activities=ACTS, n_boot=200
    )


def test_controls_real_one_zero_zero_slide_far_below_real_and_translation_changes_nothing():
    res = _run()
    r = res["models"]
    # the database holds the query's own ground truth: the real future scores 1 (g = 1 for the exact word)
    assert min(r["real"]["ndms"]) > 0.999 and r["real"]["ndms_at"]["1"][0] > 0.999
    assert r["zero"]["ndms_mean"] < 0.1  # measured 0.05: only words that include observed frames move
    assert max(r["zero"]["ndms"][8:]) < 1e-3  # words made of forecast frames only: still joints score 0
    # leave-clip-out: the real future drops below 1 (the other clips walk other headings, which the seed's
    # root-centred words keep) but stays far above the rigidly sliding pose
    assert 0.4 < r["real"]["ndms_loo_mean"] < 0.999  # measured 0.53
    assert r["slide"]["ndms_loo_mean"] < r["real"]["ndms_loo_mean"] - 0.3  # measured 0.03
    # root-centred words: sliding a still pose moves no joint, it scores as standing still; the variant with
    # words normalised at their first frame scores the root's translation (measured 0.045 against 0.51)
    assert r["slide"]["ndms"] == pytest.approx(r["zero"]["ndms"], abs=1e-4)  # float32 world coordinates
    assert np.mean(r["slide"]["ndms_word_first_frame"]) > 0.4 > r["slide"]["ndms_mean"] + 0.3
    assert r["real"]["ade"] == 0 and r["real"]["mmade"] > 0  # MMADE also scores similar-start futures
    assert r["slide"]["root_ade"] < 0.05 < r["zero"]["root_ade"]  # the toy walkers walk straight on
    assert r["slide"]["ade"] == pytest.approx(r["zero"]["ade"])  # root-centred: sliding = standing still
    assert res["n_windows_loo"] == res["n_windows"] and res["activities"]["walk0"] == "walk"
    moved = _run(SHIFT)
    for name, m in r.items():
        for key, v in m.items():
            if key == "wall_s":
                continue
            a = np.asarray(list(v.values()) if isinstance(v, dict) else v, float)
            b = np.asarray(
                list(moved["models"][name][key].values())
                if isinstance(v, dict)
                else moved["models"][name][key],
                float,
            )
            # float32 world coordinates 5 m out round at ~5e-7 m: near-tied neighbours in the leave-out search
            assert np.allclose(a, b, atol=2e-3, equal_nan=True), (name, key)


def test_ndms_scores_against_the_query_activity_only_and_checks_group_sizes():
    db = [walker(120, phase=p, speed_mps=1.2) for p in (0.0, 1.0)] + [
        walker(120, speed_mps=0.0, period_s=1.7)
    ]
    sc = M.NDMSScorer(db, NAMES, 8, groups=[0, 1, 2], activities=["walk", "walk", "step"])
    seq = walker(60, phase=0.5, speed_mps=1.2)
    assert M.ndms(sc, seq[:20], seq[20:][None], activity="walk") > M.ndms(
        sc, seq[:20], seq[20:][None], activity="step"
    )
    assert np.isnan(sc.word_scores(db[2][None], exclude_group=2, activity="step")).all()  # no other step clip
    with pytest.raises(ValueError, match="'run'"):
        sc.word_scores(seq[None], activity="run")
    with pytest.raises(ValueError, match="group 'step' has 13 motion words"):
        M.NDMSScorer([db[0], db[2][:20]], NAMES, 8, activities=["walk", "step"])


def test_cmu_activities_from_the_index_descriptions():
    assert D.activity_of_description("basketball - forward dribble, 90-degree left turns") == "basketball"
    assert D.activity_of_description("walk, shake hands (2 subjects - subject A)") == "walk"
    assert D.activity_of_description("Start Walk Stop") == "walk"
    assert D.activity_of_description("punch/strike") == "punch/strike"
    index = {
        (6, 8): "basketball - sideways dribble",
        (131, 2): "Start Walk Stop",
        (18, 1): "walk, shake hands",
    }
    clips = [D.Clip(n, walker(10), 25.0) for n in ("006_08", "scaled_131_02", "18_01", "tracks_a")]
    assert clip_activities(clips, index) == {
        "006_08": "basketball",
        "scaled_131_02": "walk",
        "18_01": "walk",
        "tracks_a": D.UNLABELLED,
    }


def test_dlow_metrics_root_centred_and_npss_reference():
    gt = walker(30, speed_mps=1.0)
    samples = np.stack([gt, gt + 0.1])
    lh, rh = D.hip_indices(NAMES)
    gc = M.root_centred(gt, lh, rh)
    assert np.allclose(M.root_centred(samples[1], lh, rh), gc)  # a shift is no pose error
    multi = M.multimodal_gt(np.stack([gc[0], gc[0] + 0.01, gc[0] + 2.0]), np.stack([gc, gc + 0.05, gc]), 0.5)
    assert [len(m) for m in multi] == [2, 2, 1]
    assert M.mmade(gc[None], multi[0]) == pytest.approx(0.5 * np.linalg.norm(np.full(57, 0.05)))
    assert M.mmfde(gc[None], multi[2]) == 0.0


def test_baseline_names_and_slide():
    assert E.check_baselines(["zero_velocity", "const", "fool", "zero"]) == ["zero", "const", "fool"]
    with pytest.raises(ValueError, match="unknown baseline 'warp'"):
        E.check_baselines(["warp"])
    from roomcap.forecast.runtime.predict import forecast_world

    obs = walker(20, speed_mps=1.5, heading_rad=0.4)
    y = forecast_world(T.baseline("slide"), obs[None, :, None], None, 25)[0, 0, :, 0]
    lh, rh = D.hip_indices(NAMES)
    v = 0.5 * (obs[-1, lh] + obs[-1, rh] - obs[-2, lh] - obs[-2, rh])
    v[2] = 0
    assert np.allclose(y[-1] - obs[-1], 25 * v, atol=1e-4)  # rigid, along the last root velocity


def test_cli_bad_protocol_and_baseline(tmp_path, capsys):
    from roomcap.forecast.cli import main

    for argv, text in (
        (["eval", "--baselines", "warp", "--out", str(tmp_path)], "unknown baseline 'warp'"),
        (["eval", "--protocol", "h36m", "--out", str(tmp_path)], "unknown protocol 'h36m'"),
        (["eval", "--protocol", "hik", str(tmp_path), "--out", str(tmp_path / "o")], "no HiK person files"),
    ):
        assert main(argv) == 2  # one message, no traceback (core.cli)
        assert text in capsys.readouterr().err


def test_social_evaluation_scores_real_two_person_clips_beside_composed_scenes(tmp_path):
    single = _clips()
    pair = np.stack([walker(100, heading_rad=0.0), walker(100, heading_rad=np.pi, start=(0.5, 4.0))], 1)
    two = D.Clip("walk_pair", pair, 25.0)
    acts = {**ACTS, "walk_pair": "walk"}
    models = {"zero": T.baseline("zero"), "const": T.baseline("const")}
    res = E.evaluate_social(
        models, single, n_obs=25, n_pred=75, n_scenes=4, real_scenes=[two], activities=acts
    )
    assert set(res["models"]) == {"zero", "const"} and res["real"]["clips"] == ["walk_pair"]
    rr = res["real"]["models"]
    assert len(rr["const"]["ndms"]) == 75 and rr["const"]["ndms_mean"] > rr["zero"]["ndms_mean"]
    assert 0 <= rr["zero"]["sscp_jsd"] <= 1
    assert "Real multi-person clips" in E.write_report(res, tmp_path).read_text()


def test_cmu_two_person_take():
    from conftest import need_shared

    need_shared("data", "motion", D.TWO_PERSON_DIR, "18_01.bvh")
    c = D.cmu_two_person_clip()
    assert c.xyz_m.shape == (63, 2, 19, 3) and c.fps == 25.0 and np.isfinite(c.xyz_m).all()
    lh, rh = D.hip_indices(NAMES)
    root = 0.5 * (c.xyz_m[:, :, lh, :2] + c.xyz_m[:, :, rh, :2])
    d = np.linalg.norm(root[:, 0] - root[:, 1], axis=-1)
    # README: hip-to-hip 1.98 m at the start, 0.74 m closest at t ~ 1.08 s, 1.80 m at the end
    assert d[0] == pytest.approx(1.98, abs=0.1) and d.min() == pytest.approx(0.74, abs=0.1)
    assert 0.9 < np.argmin(d) / 25.0 < 1.3 and d[-1] == pytest.approx(1.80, abs=0.1)


# ----------------------------------------------------------------------------- HiK (ch. 8.3)


def _smpl29(seq19: np.ndarray) -> np.ndarray:
    """Toy smpl29 poses from body19 (shared joints copied, the others at the pelvis)."""
    s29 = get_skeleton("smpl29").joint_names
    out = np.repeat(seq19[:, NAMES.index("pelvis")][:, None], 29, 1).copy()
    for j, n in enumerate(s29):
        if n in NAMES:
            out[:, j] = seq19[:, NAMES.index(n)]
    return out


def _person(path, frames, poses, onsets: dict[int, int]):
    act = np.zeros((len(frames), 82), np.float32)
    for col, at in onsets.items():
        act[at : at + 40, col] = 1
    save_npz(
        path, {"poses3d": poses.astype(np.float32), "frames": np.asarray(frames), "act": act}, compress=False
    )


def test_hik_protocol_on_a_fixture(tmp_path, capsys):
    from roomcap.forecast.cli import main
    from roomcap.forecast.lab import hik

    walk, sink = D.KITCHEN_ACTIVITIES.index("walking"), D.KITCHEN_ACTIVITIES.index("take water from sink")
    for k, kitchen in enumerate("ABD"):
        for pid in (1, 2):
            seq = _smpl29(
                walker(400, phase=pid, speed_mps=0.8 + 0.2 * pid, heading_rad=k + pid, sway_rad=SWAY)
            )
            on = {
                walk: 60,
                sink: 100 * pid,
            }  # D_2 at the sink too late for 250 future frames: short-term only
            _person(tmp_path / f"{kitchen}_{pid}_0.npz", np.arange(1000, 1400), seq, on)
    # a D person who leaves early: short-term only; the one at frame 20 lacks 50 observed frames
    _person(
        tmp_path / "D_3_0.npz", np.arange(0, 130), _smpl29(walker(130, sway_rad=SWAY)), {walk: 60, sink: 20}
    )
    res = hik.evaluate_hik(tmp_path, ["real", "zero", "const", "slide", "fool"])
    w, s = res["activities"]["walking"], res["activities"]["sink"]
    assert w["n_cases"] == 3 and w["n_cases_long"] == 2 and s["n_cases"] == 2 and s["n_cases_long"] == 1
    assert res["activities"]["coffee"]["n_cases"] == 0 and sum(res["skipped"].values()) == 1
    assert set(w["models"]) == {"real", "zero", "const", "slide"}  # the fool is body19-only
    assert w["models"]["real"]["mpjpe_at"]["25"] == 0 and w["models"]["zero"]["mpjpe_at"]["25"] > 0.1
    assert w["models"]["real"]["ndms_at"]["250"] > 0.999 and w["models"]["zero"]["ndms_at"]["250"] < 1e-3
    assert len(w["models"]["real"]["ndms"]) == 250 and len(w["models"]["real"]["mpjpe"]) == 25
    assert np.isfinite(w["models"]["real"]["ndms_loo_at"]["100"])  # the other walker of D
    assert np.isnan(s["models"]["real"]["ndms_loo_at"]["100"])  # one long sink case: no other clip
    out = tmp_path / "out"
    argv = ["eval", "--protocol", "hik", str(tmp_path), "--baselines", "real", "zero", "--out", str(out)]
    main(argv + ["--save-samples", str(out / "samples")])
    assert "| walking | 3 (2) | real | 0.0 | 0.0 | 0.0 | 1.000" in (out / "report.md").read_text()
    z = np.load(out / "samples" / "samples_zero.npz")  # the 5 short-horizon cases: 3 walking, 2 sink
    assert z["pred"].shape == (5, 1, 25, 29, 3) and z["obs"].shape[0] == 5 and z["gt"].shape == (5, 25, 29, 3)
    assert sorted(set(z["activity"])) == ["sink", "walking"] and float(z["fps"]) == D.KITCHEN_FPS
    assert len(z["clip"]) == 5 and set(z["clip"]) <= {p.stem for p in tmp_path.glob("D_*.npz")}
    # HiK files without activity flags: a clear message naming the file
    save_npz(tmp_path / "D_9_0.npz", {"poses3d": np.zeros((5, 29, 3), np.float32), "frames": np.arange(5)})
    with pytest.raises(FormatError, match="no activity flags"):
        D.load_kitchen_people(tmp_path)
    assert main(["eval", "--protocol", "hik", str(tmp_path), "--out", str(out)]) == 2
    assert "D_9_0.npz" in capsys.readouterr().err


def test_social_diffusion_generates_the_whole_horizon_in_one_pass():
    from roomcap.forecast.runtime.models import SocialDiffusion
    from roomcap.forecast.runtime.predict import diffusion_rollout, forecast_world

    m = SocialDiffusion(67, n_frames=32, channels=8, T=20)  # global statistics: not bound to its window
    m.n_obs, m.sample_steps, m.sample_eta = 16, 2, 1.0
    calls = []
    orig = m.sample_window
    m.sample_window = lambda *a, **k: calls.append(k.get("n_frames")) or orig(*a, **k)
    scene = np.stack([walker(16), walker(16, start=(2, 0))], 1)[None]
    assert diffusion_rollout(m, 100) == "one_pass"
    y = forecast_world(m, scene, None, 100, n_samples=2)
    assert y.shape == (1, 2, 100, 2, 19, 3) and np.isfinite(y).all() and calls == [128]  # one window of 128
    calls.clear()
    forecast_world(m, scene, None, 40, n_samples=1, mode="chained")  # the ablation: windows of 32
    assert calls == [None, None, None]
    anchored = SocialDiffusion(67, n_frames=32, channels=8, T=20, anchored=True)
    anchored.n_obs = 16
    assert diffusion_rollout(anchored, 16) == "one_pass" and diffusion_rollout(anchored, 40) == "chained"
    with pytest.raises(ValueError, match="per-frame statistics"):
        anchored.sample_window(torch.zeros(1, 1, 16, 67), torch.ones(1, 1, dtype=torch.bool), n_frames=64)


def test_one_results_schema_and_one_renderer(tmp_path):
    """lab.protocol: a protocol's figures and its tables in one results.json schema, one Markdown renderer."""
    import json

    from roomcap.core.errors import FormatError
    from roomcap.forecast.lab import protocol as P

    t = P.Table("Average", ["model", "80 ms"], [["zero", *P.cells([25.94])], ["ours", *P.cells([None])]])
    res = P.results(
        "toy", "A toy protocol", ["Reference: none."], [t], ["- source"], models={"zero": [25.94]}
    )
    assert (
        res["schema"] == P.RESULTS_SCHEMA and res["protocol"] == "toy" and res["models"] == {"zero": [25.94]}
    )
    md = P.render(res)
    assert md.startswith(
        "# A toy protocol\n\nReference: none.\n\n## Average\n\n| model | 80 ms |\n|---|---|\n"
    )
    assert "| zero | 25.9 |\n| ours | - |\n" in md and md.endswith("- source\n")
    path = P.write(res, tmp_path / "o")
    assert path.read_text() == md and json.loads((tmp_path / "o" / "results.json").read_text()) == res
    with pytest.raises(FormatError, match="forecast-results/1"):
        P.render({"models": {}})
    assert all(v[2] for v in P.PROTOCOLS.values()) and len(P.PROTOCOLS) == 8
