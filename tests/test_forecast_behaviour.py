"""The behaviour forecaster (Diller ch. 4): label files, geometry, model, composite data, sample."""

from __future__ import annotations

import dataclasses
import doctest
import io

import numpy as np
import pytest
import torch

from roomcap.core.errors import FormatError, InputError
from roomcap.forecast.lab.behaviour import geometry, labels
from roomcap.forecast.lab.behaviour.data import ACTIONS, JOINTS, PARENTS, SCRIPT, action_of_description
from roomcap.forecast.lab.behaviour.model import (
    BehaviourConfig,
    bones,
    build,
    gram,
    load_checkpoint,
    rollout,
    save_checkpoint,
)
from roomcap.synthetic.rigs import ring_rig
from tests.conftest import need_shared

torch.set_num_threads(1)


def test_label_doctest():
    assert doctest.testmod(labels).failed == 0


def _csv(text: str):
    f = io.StringIO(text)
    f.name = "labels.csv"
    return f


def test_label_file_errors():
    with pytest.raises(FormatError, match="header"):
        labels.read_labels(_csv("id,start,end,label\n0,0,1,walk\n"))
    with pytest.raises(FormatError, match="line 2"):
        labels.read_labels(_csv("track_id,start_s,end_s,label\n0,zero,1,walk\n"))
    with pytest.raises(FormatError, match="start_s < end_s"):
        labels.read_labels(_csv("track_id,start_s,end_s,label\n0,2,1,walk\n"))
    with pytest.raises(FormatError, match=r"overlap: line 2 .* line 3"):
        labels.read_labels(_csv("track_id,start_s,end_s,label\n0,0,2,walk\n0,1.5,3,sit\n1,0,2,sit\n"))
    # the same times on two different people are not an overlap
    rows = labels.read_labels(_csv("track_id,start_s,end_s,label\n0,0,2,walk\n1,0,2,sit\n"))
    assert [r.track_id for r in rows] == [0, 1]


def test_action_rules_and_script():
    assert action_of_description("sit on high stool, stand up") == "sit"
    assert action_of_description("unscrew bottlecap, drink soda") == "drink"
    assert action_of_description("walk on uneven terrain") == "walk"
    assert action_of_description("basketball - forward dribble") is None
    for a, nxt in SCRIPT.items():
        assert a in ACTIONS and a not in nxt and set(nxt) <= set(ACTIONS)


def _view(rng, S=4):
    rig = ring_rig(6, 4.0, height_m=2.2)
    cams = [rig[int(i)] for i in rng.integers(6, size=S)]
    K = np.stack([c.K for c in cams])
    R = np.stack([c.R for c in cams])
    t = np.stack([c.t for c in cams])
    g = np.c_[rng.uniform(-1, 1, (S, 2)), np.zeros(S)]
    return geometry.make_view(K, R, t, g)


def test_plane_features_agree_with_projection(rng):
    """A 3D pose projected into its camera and met with the person's plane gives the same plane features
    as the differentiable perspective of the 3D pose (numpy and torch paths agree)."""
    v = _view(rng)
    P = rng.normal(0, 0.3, (4, 19, 3)) + np.array([0, 0, 1.0])  # viewer frame, around the anchor
    tv = v.torch()
    X = geometry.to_world(torch.as_tensor(P, dtype=torch.float32), tv["V"], tv["g"])
    px = geometry.project(X, tv["K"], tv["R"], tv["t"]).numpy()
    f_np = geometry.plane_features(v, px[:, None].astype(np.float64))[:, 0]
    f_t = geometry.plane_of_3d(torch.as_tensor(P, dtype=torch.float32), tv["c"]).numpy()
    assert np.abs(f_np - f_t).max() < 2e-3  # measured ~1e-5 m
    # points on the plane map to themselves (x, z)
    onp = P.copy()
    onp[..., 1] = 0
    Xo = geometry.to_world(torch.as_tensor(onp, dtype=torch.float32), tv["V"], tv["g"])
    pxo = geometry.project(Xo, tv["K"], tv["R"], tv["t"]).numpy()
    fo = geometry.plane_features(v, pxo[:, None].astype(np.float64))[:, 0]
    assert np.abs(fo - onp[..., [0, 2]]).max() < 1e-3


def test_project_matches_camera(rng):
    cam = ring_rig(6, 4.0, height_m=2.2)[2]
    X = rng.uniform(-1, 1, (1, 30, 3)) + np.array([0, 0, 1.0])
    px = geometry.project(
        torch.as_tensor(X),
        torch.as_tensor(cam.K.copy())[None],
        torch.as_tensor(cam.R.copy())[None],
        torch.as_tensor(cam.t.copy())[None],
    ).numpy()[0]
    assert np.abs(px - cam.project(X[0])).max() < 1e-6


def test_anchor_from_ankles(rng):
    v = _view(rng)
    ank = np.array([[0.1, 0.05, geometry.ANKLE_HEIGHT_M], [-0.1, -0.05, geometry.ANKLE_HEIGHT_M]])
    xy = np.stack([np.stack([v.K[s] @ (v.R[s] @ (a + v.g[s]) + v.t[s]) for a in ank]) for s in range(4)])
    xy = xy[..., :2] / xy[..., 2:]
    g = geometry.anchor_from_2d(v.K, v.R, v.t, xy, (0, 1))
    assert np.abs(g - v.g).max() < 1e-6


def test_gram_has_squared_bone_lengths(rng):
    b = bones(JOINTS)
    assert len(b) == 18 and all(PARENTS[c] == p for c, p in b)
    P = torch.as_tensor(rng.normal(size=(3, 19, 3)), dtype=torch.float32)
    G = gram(P, torch.as_tensor(b))
    nb = len(b)
    iu = torch.triu_indices(nb, nb)
    diag = G[:, iu[0] == iu[1]]
    L2 = ((P[:, b[:, 0]] - P[:, b[:, 1]]) ** 2).sum(-1)
    assert torch.allclose(diag, L2, atol=1e-5)
    assert len(bones(tuple(n for n in JOINTS if n in ("neck", "pelvis", "nose", "left_wrist")))) == 3


@pytest.mark.parametrize("variant", ["full", "action_only", "pose_only"])
def test_rollout_is_autoregressive(variant):
    cfg = BehaviourConfig(variant=variant, hidden=32, m=4)
    gen, critic = build(cfg)
    B, N, J, A = 5, cfg.n_obs, 19, len(ACTIONS)
    feats = torch.randn(B, N, J, 2)
    seen = torch.ones(B, N, J, dtype=torch.bool)
    acts = torch.randint(A, (B, N))
    c = torch.tensor([[0.0, -4.0, 2.2]]).repeat(B, 1)
    lg, P = rollout(gen, feats, acts, seen, c, cfg.m, feed_pose=cfg.use_pose, feed_action=cfg.use_action)
    assert lg.shape == (B, cfg.m, A) and P.shape == (B, cfg.m, J, 3)
    assert critic(P[:, 0]).shape == (B,)
    # the second step depends on the first step's prediction only through what is fed back
    lg2, _ = rollout(gen, feats, acts, seen, c, 1)
    assert torch.allclose(lg2[:, 0], lg[:, 0], atol=1e-6)
    assert not torch.allclose(lg[:, 1], lg[:, 0])


def test_checkpoint_round_trip(tmp_path):
    cfg = BehaviourConfig(hidden=32)
    gen, _ = build(cfg)
    path = tmp_path / "b.pt"
    save_checkpoint(path, {"full": gen}, {"full": cfg}, {"action_freq": [1 / len(ACTIONS)] * len(ACTIONS)})
    blob = torch.load(path, weights_only=True)
    assert blob["schema"] == "forecast-checkpoint/2" and blob["model"] == "behaviour"
    gens, cfgs, extra = load_checkpoint(path)
    assert cfgs["full"] == cfg
    for a, b in zip(gens["full"].parameters(), gen.parameters(), strict=True):
        assert torch.equal(a, b)
    (tmp_path / "bad.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(FormatError, match="behaviour checkpoint"):
        load_checkpoint(tmp_path / "bad.pt")


def test_composite_sequences_from_cmu():
    need_shared("data", "motion", "cmu-more", "single", "14")
    from roomcap.forecast.lab.behaviour import data
    from roomcap.forecast.lab.behaviour.training import prepare

    pool = data.split_pool(data.load_pool())
    subj = {p: {c.subject for c in v} for p, v in pool.items()}
    assert not (subj["train"] & subj["test"]) and not (set(data.DB_SUBJECTS) & (subj["train"] | subj["test"]))
    for p in ("train", "val", "test"):
        assert {c.action for c in pool[p]} == set(ACTIONS), p
    comp = data.make_composite(pool["test"], 40, 8, seed=1)
    # every step follows the script
    for row in comp.actions:
        for a, b in zip(row[:-1], row[1:], strict=True):
            assert ACTIONS[b] in SCRIPT[ACTIONS[a]]
    # the 2D is the rendering of the 3D: seen joints lie near the projection (noise 2 px, distortion)
    cam = comp.rig[int(comp.cam[0])]
    proj = cam.project(comp.xyz_m[0].reshape(-1, 3)).reshape(8, 19, 2)
    ok = np.isfinite(comp.xy_px[0, ..., 0])
    assert ok.mean() > 0.6
    assert np.median(np.linalg.norm(comp.xy_px[0][ok] - proj[ok], axis=-1)) < 5.0  # measured ~2.5 px
    d = prepare(comp, 3, 5)
    assert d.feats.shape == (40, 3, 19, 2) and d.tgt_3d.shape == (40, 5, 19, 3)
    # the anchor is the floor under the person where the feet stand on it (climbing and sitting on a stool
    # lift the ankles, which moves the anchor away: measured ~0.6-0.8 m there)
    pel = comp.xyz_m[:, 2, JOINTS.index("pelvis"), :2]
    ank = comp.xyz_m[:, 2, [JOINTS.index("left_ankle"), JOINTS.index("right_ankle")], 2].min(1)
    err = np.linalg.norm(d.view.g[:, :2] - pel, axis=1)
    assert np.median(err[ank < 0.15]) < 0.3  # measured 0.15 m


# ----------------------------------------------------------------------------- sample on a session


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    """A synthetic two-person session (procedural walkers, a ring rig) with its ground truth as the
    track file, and an untrained checkpoint."""
    from roomcap.synthetic.render import render
    from roomcap.synthetic.rigs import ring_room
    from roomcap.synthetic.world import make_scene, write_session
    from roomcap.track.trackfile import TrackFile

    root = tmp_path_factory.mktemp("sess")
    rig = ring_rig(4, 4.0, height_m=2.2)
    scene = make_scene(ring_room(4.0), n_people=2, duration_s=6.0, fps=25.0, motion="procedural", seed=2)
    write_session(scene, render(scene, rig, noise_px=1.0), rig, root / "s")
    T = scene.n_frames
    xyz = scene.gt_xyz_m.astype(np.float32)
    tf = TrackFile(
        fps=25.0,
        frame_index=np.arange(T),
        t_ns=(np.arange(T) * 4e7).astype(np.int64),
        track_id=np.array([3, 7]),
        joint_names=JOINTS,
        parents=np.asarray(PARENTS),
        xyz_m=xyz,
        confidence=np.ones(xyz.shape[:3], np.float32),
        std_m=np.zeros(xyz.shape[:3], np.float32),
        flags=np.ones(xyz.shape[:3], np.uint8),
    )
    (root / "s" / "track").mkdir()
    tf.save(root / "s" / "track" / "tracks.npz")
    cfg = BehaviourConfig(hidden=32)
    gen, _ = build(cfg)
    save_checkpoint(
        root / "b.pt", {"full": gen}, {"full": cfg}, {"action_freq": [1 / len(ACTIONS)] * len(ACTIONS)}
    )
    return root, scene


def test_sample_writes_forecast(session):
    from roomcap.forecast.lab.behaviour.sample import run_sample

    root, scene = session
    lab = root / "labels.csv"
    lab.write_text(
        "track_id,start_s,end_s,label\n3,0,1.5,walk\n3,1.5,3.5,sit\n3,3.5,5.9,drink\n7,0.5,4,walk\n"
    )
    out = run_sample(root / "s", lab, root / "behaviour.npz", checkpoint=root / "b.pt")
    d = np.load(out, allow_pickle=False)
    K, M, A = 2, 5, len(ACTIONS)
    assert d["track_id"].tolist() == [3, 7] and d["labels"].tolist() == list(ACTIONS)
    assert d["actions"].shape == (K, M) and set(d["actions"].ravel()) <= set(ACTIONS)
    assert d["probs"].shape == (K, M, A) and np.allclose(d["probs"].sum(-1), 1, atol=1e-5)
    assert d["poses_m"].shape == (K, M, 19, 3) and np.isfinite(d["poses_m"]).all()
    ank = d["poses_m"][..., [JOINTS.index("left_ankle"), JOINTS.index("right_ankle")], 2].min(-1)
    assert np.allclose(ank, 0.08, atol=1e-5)  # standing on the floor
    assert d["observed"].tolist()[0] == ["walk", "sit", "drink"] and d["observed"].tolist()[1][-1] == "walk"
    assert d["step_start_s"][0].tolist() == [0, 1.5, 3.5] and d["step_end_s"][0].tolist() == [1.5, 3.5, 5.9]
    assert d["step_end_s"][1, -1] == 4 and np.isnan(d["step_start_s"][1, :-1]).all()
    # the forecast poses stand in the room near where each person was last seen (untrained: within 3 m)
    last = scene.gt_xyz_m[int(round(5.9 * 25)) - 1, 0, JOINTS.index("pelvis"), :2]
    assert np.linalg.norm(d["poses_m"][0, :, JOINTS.index("pelvis"), :2].mean(0) - last) < 3.0


@pytest.mark.parametrize(
    ("text", "match"),
    [
        (
            "track_id,start_s,end_s,label\n3,0,1,walk\n9,0,1,walk\n",
            r"bad.csv, line 3: track id 9 matches no track of the session \(its tracks: \[3, 7\]\)",
        ),
        (
            "track_id,start_s,end_s,label\n3,0,1,walk\n3,1,2,dance\n7,1,2,sit\n7,2,3,juggle\n",
            r"bad.csv, lines 3, 5: label 'dance' is unknown to the model",
        ),
        ("track_id,start_s,end_s,label\n3,30,40,walk\n", "line 2: track 3 has no 3D between 30.0 and 40.0 s"),
        ("track_id,start_s,end_s,label\n7,0,1,sit\n3,0,2,walk\n3,1,3,sit\n", "overlap: line 3 .* line 4"),
    ],
)
def test_sample_bad_labels(session, text, match):
    from roomcap.forecast.lab.behaviour.sample import run_sample

    root, _ = session
    lab = root / "bad.csv"
    lab.write_text(text)
    with pytest.raises((InputError, FormatError), match=match):
        run_sample(root / "s", lab, root / "x.npz", checkpoint=root / "b.pt")


def test_sample_needs_tracks(session, tmp_path, capsys):
    """A session without a track file, or with one that holds no track, says to run the track stage first."""
    import shutil

    from roomcap.forecast.lab.behaviour.cli import main
    from roomcap.track.trackfile import TrackFile

    root, _ = session
    s = tmp_path / "notracks"
    shutil.copytree(root / "s", s)
    (s / "track" / "tracks.npz").unlink()
    lab = tmp_path / "l.csv"
    lab.write_text("track_id,start_s,end_s,label\n3,0,1,walk\n")
    argv = ["sample", str(s), "--labels", str(lab), "--checkpoint", str(root / "b.pt")]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "run the track stage first" in err and "forecast behaviour sample SESSION --labels FILE" in err
    tf = TrackFile.load(root / "s" / "track" / "tracks.npz")
    empty = dataclasses.replace(
        tf,
        track_id=tf.track_id[:0],
        xyz_m=tf.xyz_m[:, :0],
        confidence=tf.confidence[:, :0],
        std_m=tf.std_m[:, :0],
        flags=tf.flags[:, :0],
    )
    empty.save(s / "track" / "tracks.npz")
    assert main(argv) == 2
    assert "holds no tracks; run the track stage first" in capsys.readouterr().err


def test_sample_needs_a_rig(session, tmp_path):
    import shutil

    from roomcap.forecast.lab.behaviour.cli import main

    root, _ = session
    s = tmp_path / "norig"
    shutil.copytree(root / "s", s)
    (s / "calib" / "rig.toml").unlink()
    lab = tmp_path / "l.csv"
    lab.write_text("track_id,start_s,end_s,label\n3,0,1,walk\n")
    assert main(["sample", str(s), "--labels", str(lab), "--checkpoint", str(root / "b.pt")]) == 2


def test_hide_history_hides_only_the_first_steps():
    from roomcap.forecast.lab.behaviour.training import hide_history

    cfg = BehaviourConfig(short_history=1.0)
    B, N = 64, cfg.n_obs
    tb = {
        "seen": torch.ones(B, N, 19, dtype=torch.bool),
        "feats": torch.ones(B, N, 19, 2),
        "obs_acts": torch.zeros(B, N, dtype=torch.long),
    }
    hide_history(tb, cfg, torch.Generator().manual_seed(0))
    hidden = ~tb["seen"].any(-1)
    assert hidden.any(1).all() and not hidden[:, -1].any()  # every sequence keeps its last step
    assert (tb["obs_acts"][hidden] == len(ACTIONS)).all() and (tb["feats"][hidden] == 0).all()
    # hidden steps are a prefix
    assert (hidden[:, 1:] <= hidden[:, :-1]).all()


def test_report_shows_the_behaviour_forecast(session, tmp_path):
    """The session report lists each person's observed and forecast actions when behaviour.npz is there."""
    import re

    from roomcap.capture.session import SessionLayout
    from roomcap.forecast.lab.behaviour.sample import run_sample
    from roomcap.pipeline.report import collect, write_report
    from tests.test_pipeline_report import CHROMIUM, page_errors, render_in_browser

    root, _ = session
    lab = root / "rep.csv"
    lab.write_text("track_id,start_s,end_s,label\n3,0,2,walk\n3,2,4,sit\n7,0,3,climb\n")
    run_sample(root / "s", lab, checkpoint=root / "b.pt")  # default: SESSION/forecast/behaviour.npz
    lay = SessionLayout(root / "s")
    b = collect(lay, "t")["behaviour"]
    assert b["track_id"] == [3, 7] and b["observed"][0][-2:] == ["walk", "sit"] and len(b["actions"][0]) == 5
    # the timeline's data: the labelled ranges of the observed steps, every label's probability per step
    K, M, A, N = 2, 5, len(ACTIONS), len(b["observed"][0])
    assert b["labels"] == list(ACTIONS)
    probs = np.asarray(b["probs"], float)
    assert probs.shape == (K, M, A) and np.allclose(probs.sum(-1), 1, atol=5e-3)
    assert (
        np.allclose(probs.max(-1), b["prob"]) and [ACTIONS[j] for j in probs[0].argmax(-1)] == b["actions"][0]
    )
    start, end = (np.asarray(b[k], float) for k in ("step_start_s", "step_end_s"))
    assert start.shape == end.shape == (K, N)
    assert start[0, -2:].tolist() == [0, 2] and end[0, -2:].tolist() == [2, 4] and end[1, -1] == 3
    assert np.isnan(start[1, :-1]).all()  # track 7 has one labelled step
    # the forecast characteristic poses, in the room, with a skeleton to draw them
    poses = np.asarray(b["poses"], float)
    assert poses.shape == (K, M, 19, 3) and np.isfinite(poses).all()
    assert b["joint_names"] == list(JOINTS) and len(b["parents"]) == 19
    assert sorted(p for p in b["parents"] if p < 0) == [-1] and b["parents"][JOINTS.index("left_knee")] == (
        JOINTS.index("left_hip")
    )
    if CHROMIUM is None:
        pytest.skip("headless Chromium not installed")
    path = write_report(lay, title="behaviour")
    _, dom = render_in_browser(path, tmp_path, height=3000)
    assert page_errors(dom) == "", page_errors(dom)
    assert 'data-behaviour="2"' in dom and 'id="behavsec" style="display: block;"' in dom
    assert dom.count('class="step') == M  # one button per forecast step (the pose drawn in 3D)
    body = dom.split('id="behaviour"', 1)[1].split("</table>", 1)[0]
    rows = [re.findall(r"<td[^>]*>(.*?)</td>", tr) for tr in re.findall(r"<tr[^>]*>(.*?)</tr>", body, re.S)]
    rows = [r for r in rows if r]
    assert [r[0] for r in rows] == ["3", "7"] and rows[0][1] == "walk → sit" and len(rows[0]) == 2 + 5
    assert all(re.fullmatch(r"[a-z]+ \(\d+%\)", c) for c in rows[0][2:])


def test_session_windows_from_a_label_file(session):
    """A user's session with labels gives training windows: n_obs + M consecutive labelled steps per track,
    with the detections as 2D targets and the track's 3D."""
    from roomcap.forecast.lab.behaviour.sample import session_windows
    from roomcap.forecast.lab.behaviour.training import concat

    root, scene = session
    acts = ["walk", "sit", "drink", "laugh", "walk", "climb", "reach", "wash", "walk"]
    lines = [f"3,{0.65 * i:.2f},{0.65 * (i + 1):.2f},{a}" for i, a in enumerate(acts[:8])]
    lines += [f"7,{0.6 * i:.2f},{0.6 * (i + 1):.2f},{a}" for i, a in enumerate(acts)]
    lab = root / "train.csv"
    lab.write_text("track_id,start_s,end_s,label\n" + "\n".join(lines) + "\n")
    d = session_windows(root / "s", lab, 3, 5)
    assert len(d) == 1 + 2  # 8 steps: one window; 9 steps: two
    assert d.acts[0].tolist() == [ACTIONS.index(a) for a in acts[:8]]
    assert (
        d.feats.shape == (3, 3, 19, 2) and d.tgt_px.shape == (3, 5, 19, 2) and d.tgt_3d.shape == (3, 5, 19, 3)
    )
    assert d.seen.mean() > 0.5 and np.isfinite(d.tgt_px).mean() > 0.5
    # the 3D targets are the track's poses in the viewer frame: bone lengths are kept
    X = d.tgt_3d[0]
    gt_len = np.linalg.norm(scene.gt_xyz_m[:, 0, 9] - scene.gt_xyz_m[:, 0, 7], axis=-1)
    assert np.allclose(np.linalg.norm(X[:, 9] - X[:, 7], axis=-1), np.nanmedian(gt_len), atol=0.02)
    assert len(concat([d, d])) == 6
    short = root / "short.csv"
    short.write_text("track_id,start_s,end_s,label\n3,0,1,walk\n")
    with pytest.raises(InputError, match="no track has 8 labelled steps"):
        session_windows(root / "s", short, 3, 5)


def test_continuous_activity_session(tmp_path):
    """Continuous composite activities (blended transitions) make a session with a label file that the
    user-data path reads: labels tile the motion, each step's characteristic frame lies in its range."""
    need_shared("data", "motion", "cmu-more", "single", "13")
    from roomcap.forecast.lab.behaviour import data
    from roomcap.forecast.lab.behaviour.sample import session_windows

    pool = data.split_pool(data.load_pool())["test"]
    a = data.compose_continuous(pool, 8, seed=3)
    assert len(a.labels) == 8 and np.allclose(a.start_s[1:], a.end_s[:-1]) and a.start_s[0] == 0
    t = a.char_frame / a.fps
    assert ((t >= a.start_s) & (t < a.end_s)).all()
    speed = np.linalg.norm(np.diff(a.xyz_m, axis=0), axis=-1).max(-1) * a.fps
    assert speed.max() < 8.0  # no jump at the joins (measured 4.3 m/s peak, a hand)
    rig = ring_rig(3, 4.0, height_m=2.2)
    lay, lab = data.activity_session(pool, tmp_path / "s", n_people=2, length=8, seed=1, rig=rig)
    d = session_windows(lay.root, lab, 3, 5)
    assert len(d) == 2 and d.seen.mean() > 0.6


def test_continuous_activity_session_follows_the_stations_script(tmp_path):
    """Continuous activities of the "stations" script: the steps follow its chain, a step at a place has its
    characteristic pose there, the glides between places keep a walking pace, and the session it makes is
    read by the user-data path."""
    need_shared("data", "motion", "cmu-more", "single", "13")
    from roomcap.forecast.lab.behaviour import data
    from roomcap.forecast.lab.behaviour.sample import session_windows

    pool = data.split_pool(data.load_pool())["test"]
    a = data.compose_continuous(pool, 8, seed=3, script="stations")
    ch = data.script_chain("stations")
    ix = [ch.states.index(s) for s in a.states]
    assert len(ix) == 8 and all(ch.T[i, j] > 0 for i, j in zip(ix[:-1], ix[1:], strict=True))
    assert list(a.labels) == [ACTIONS[ch.action[i]] for i in ix]
    assert np.allclose(a.start_s[1:], a.end_s[:-1]) and a.start_s[0] == 0
    t = a.char_frame / a.fps
    assert ((t >= a.start_s) & (t < a.end_s)).all()
    pel = a.xyz_m[a.char_frame, JOINTS.index("pelvis"), :2]
    for s, xy in zip(a.states, pel, strict=True):
        place = s.split(":")[0]
        if place != "walk":  # at its place (s.d. 0.2 m)
            assert np.linalg.norm(xy - data.STATIONS[place][0]) < 0.9, (s, xy)
    speed = np.linalg.norm(np.diff(a.xyz_m[:, JOINTS.index("pelvis")], axis=0), axis=-1) * a.fps
    assert np.median(speed) < 2.0 and speed.max() < 8.0
    with pytest.raises(ValueError, match="script must be one of"):
        data.compose_continuous(pool, 3, script="nope")
    rig = ring_rig(3, 4.0, height_m=2.2)
    lay, lab = data.activity_session(
        pool, tmp_path / "s", n_people=2, length=8, seed=1, rig=rig, script="stations"
    )
    d = session_windows(lay.root, lab, 3, 5)
    assert len(d) == 2 and d.seen.mean() > 0.5


def test_merge_joins_variants(tmp_path, capsys):
    from roomcap.forecast.lab.behaviour.cli import main

    extra = {"action_freq": [1 / len(ACTIONS)] * len(ACTIONS), "avg_pose": [[0.0, 0.0, 1.0]] * 19}
    for v in ("full", "action_only"):
        cfg = BehaviourConfig(variant=v, hidden=16)
        gen, _ = build(cfg)
        save_checkpoint(tmp_path / f"{v}.pt", {v: gen}, {v: cfg}, {**extra, "history": {v: {"best_step": 1}}})
    out = tmp_path / "both.pt"
    assert (
        main(["merge", str(tmp_path / "full.pt"), str(tmp_path / "action_only.pt"), "--out", str(out)]) == 0
    )
    gens, cfgs, ex = load_checkpoint(out)
    assert sorted(gens) == ["action_only", "full"] and cfgs["action_only"].variant == "action_only"
    assert sorted(ex["history"]) == ["action_only", "full"]
    assert main(["merge", str(tmp_path / "full.pt"), str(tmp_path / "full.pt"), "--out", str(out)]) == 2
    assert "again" in capsys.readouterr().err


def test_train_and_eval_commands_tiny(tmp_path):
    """`train` then `eval` end to end at a tiny scale: every method of Table 4.1 gets its figures."""
    import json

    need_shared("data", "motion", "cmu-more", "single", "14")
    from roomcap.forecast.lab.behaviour.cli import main

    ck, res = tmp_path / "t.pt", tmp_path / "r.json"
    sets = ["steps=4", "eval_every=2", "n_train=120", "n_eval=60", "hidden=16"]
    assert main(["train", "--out", str(ck), "--eval-split", "none", "--set", *sets]) == 0
    assert main(["eval", "--checkpoint", str(ck), "--split", "val", "--out", str(res)]) == 0
    models = json.loads(res.read_text())["models"]
    assert sorted(models) == [
        "action_2d",
        "action_only",
        "full",
        "pose_only",
        "train_average",
        "true_3d",
        "zero_velocity",
    ]
    assert models["full"]["mpjpe2d_px"] > 0 and 0 <= models["full"]["quality3d"] <= 1
    assert 0 <= models["full"]["quality3d_per_method"] <= 0.5
    assert models["action_only"]["mpjpe2d_px"] is None and models["pose_only"]["top1"] is None
    assert len(models["full"]["top1_by_step"]) == 5
