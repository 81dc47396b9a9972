"""Forecast data: normalisation (eq. 3.8), windows with gaps/NaNs, track files, Humans-in-Kitchens adapter."""

from __future__ import annotations

import numpy as np
import pytest

from roomcap.core.errors import FormatError, SchemaError
from roomcap.core.fileio import save_npz
from roomcap.forecast.lab import data as D
from roomcap.forecast.lab.toy import walker
from roomcap.keypoints.skeletons import get_skeleton
from roomcap.track.trackfile import TrackFile


def test_normalisation_puts_hips_on_x_and_inverts(rng):
    x = walker(40, heading_rad=1.1, start=(2.0, -1.0))
    x = x + rng.normal(0, 0.01, x.shape).astype(np.float32)
    R, root = D.norm_frame(x[-1], 11, 12)
    y = D.normalize(x, R, root)
    hv = y[-1, 12] - y[-1, 11]
    assert abs(hv[1]) < 1e-5 and hv[0] > 0  # hip vector on +x
    assert np.allclose(0.5 * (y[-1, 11] + y[-1, 12]), 0, atol=1e-5)  # root at the origin
    assert np.allclose(y[..., 2], x[..., 2] - root[2], atol=1e-5)  # z stays up
    assert np.abs(D.denormalize(y, R, root) - x).max() < 1e-5


def test_windows_mask_gaps_and_skip_short_clips():
    x = walker(120)[:, None].copy()
    x[30:35, 0, 9] = np.nan  # a gap in the left wrist
    x[59, 0, :] = np.nan  # a whole frame missing
    clips = [D.Clip("a", x, 25.0), D.Clip("short", walker(15), 25.0)]
    ws = D.make_windows(clips, 10, 10, stride=5)
    assert ws.skipped["clip_shorter_than_window"] == 1
    assert np.isfinite(ws.x).all()
    # windows whose last observed frame is frame 59 are skipped (no hips to normalise on)
    assert ws.skipped["no_person_at_last_observed_frame"] == 1
    w = np.flatnonzero(ws.start == 25)[0]
    assert not ws.mask[w, 5:10, 0, 9].any() and ws.mask[w, 5:10, 0, 10].all()


def test_resample_120_to_25():
    c = D.Clip("a", walker(240, fps=120.0), 120.0).resampled(25.0)
    assert c.fps == 25.0 and c.n_frames == 50
    ref = walker(50, fps=25.0)
    assert np.abs(c.xyz_m[:, 0] - ref).max() < 0.01


def _trackfile(path, xyz, fps=25.0):
    T, K = xyz.shape[:2]
    sk = get_skeleton("body19")
    tf = TrackFile(
        fps=fps,
        frame_index=np.arange(T),
        t_ns=(np.arange(T) * 1e9 / fps).astype(np.int64),
        track_id=np.arange(K),
        joint_names=sk.joint_names,
        parents=np.asarray(sk.parents),
        xyz_m=xyz,
        confidence=np.isfinite(xyz).all(-1).astype(np.float32),
        std_m=np.full(xyz.shape[:3], 0.02),
        flags=np.ones(xyz.shape[:3], np.uint8),
    )
    tf.save(path)
    return path


def test_trackfile_with_nans_and_bad_schema(tmp_path):
    xyz = np.stack([walker(80), walker(80, start=(2, 0), heading_rad=3.0)], 1)
    xyz[20:40, 1] = np.nan  # person 2 leaves for 0.8 s
    xyz[5, 0, 3] = np.nan
    clip = D.clip_from_trackfile(_trackfile(tmp_path / "tracks.npz", xyz))
    assert clip.xyz_m.shape == (80, 2, 19, 3)
    ws = D.make_windows([clip], 20, 10, 5, persons="all")
    assert np.isfinite(ws.x).all() and ws.person_mask.shape[1] == 2
    assert (~ws.person_mask[:, 1]).sum() > 0  # windows where person 2 is absent at the last observed frame
    data = dict(np.load(tmp_path / "tracks.npz"))
    data["schema"] = np.asarray("tracks/99")
    save_npz(tmp_path / "bad.npz", data)
    with pytest.raises(SchemaError, match="99"):
        D.clip_from_trackfile(tmp_path / "bad.npz")


def _kitchen_npz(path, frames, rng):
    n = len(frames)
    save_npz(
        path,
        {
            "poses3d": rng.normal(0, 0.3, (n, 29, 3)).astype(np.float32) + [0, 0, 1],
            "frames": np.asarray(frames),
            "act": np.zeros((n, 82), np.float32),
            "transforms": np.zeros((n, 6), np.float32),
            "smpl": np.zeros((n, 21, 3), np.float32),
            "betas": np.zeros(10, np.float32),
        },
        compress=False,
    )
    return path


def test_kitchens_adapter(tmp_path, rng):
    a = _kitchen_npz(tmp_path / "p0.npz", np.arange(100, 150), rng)
    b = _kitchen_npz(tmp_path / "p1.npz", np.arange(120, 180), rng)
    seg = D.load_kitchens_npz(a)
    assert seg["poses3d"].shape == (50, 29, 3) and seg["act"].shape == (50, 82)
    scene = D.kitchens_scene([a, b])
    assert scene.skeleton == "smpl29" and scene.fps == 25.0 and scene.xyz_m.shape == (80, 2, 29, 3)
    assert np.isnan(scene.xyz_m[60:, 0]).all() and np.isfinite(scene.xyz_m[:50, 0]).all()
    assert np.isnan(scene.xyz_m[:20, 1]).all()
    b19 = D.smpl29_to_body19(seg["poses3d"])
    names = get_skeleton("body19").joint_names
    assert np.allclose(b19[:, names.index("left_wrist")], seg["poses3d"][:, 20])  # SMPL joint 20 = left_wrist
    assert np.isnan(b19[:, names.index("nose")]).all()
    ws = D.make_windows([scene], 10, 10, 5, persons="all")
    assert len(ws) > 0 and ws.skeleton == "smpl29"
    save_npz(tmp_path / "bad.npz", {"poses3d": np.zeros((5, 22, 3)), "frames": np.arange(5)})
    with pytest.raises(FormatError, match="29"):
        D.load_kitchens_npz(tmp_path / "bad.npz")


def test_cmu_clip_through_synthetic_bvh():
    from conftest import need_shared

    need_shared("data", "motion", "cmu-bvh-01", "01_01.bvh")
    c = D.clip_from_bvh(D.cmu_bvh_files()[0])
    assert c.fps == 25.0 and c.xyz_m.shape[1:] == (1, 19, 3) and c.n_frames > 100
    height = np.nanmax(c.xyz_m[..., 2]) - np.nanmin(c.xyz_m[..., 2])
    assert 1.2 < height < 2.3  # a person, in metres, z up


def test_train_val_test_split_by_clip_is_deterministic_and_stratified():
    names = [f"c{i:02d}" for i in range(40)]
    lengths = [60 + 10 * i for i in range(40)]
    tr, va, te = D.split_train_val_test(names, lengths)
    assert sorted(tr + va + te) == list(range(40)) and not (
        set(tr) & set(va) | set(tr) & set(te) | set(va) & set(te)
    )
    assert (len(tr), len(va), len(te)) == (25, 5, 10)
    # the long clips (the only ones long enough for 6 s evaluation windows) are spread over the splits
    long = set(range(30, 40))
    assert len(long & set(te)) >= 2 and len(long & set(va)) >= 1
    # the split depends on names and lengths, not on the order they are listed in
    perm = np.random.default_rng(1).permutation(40)
    tr2, va2, te2 = D.split_train_val_test([names[i] for i in perm], [lengths[i] for i in perm])
    assert sorted(names[perm[i]] for i in te2) == sorted(names[i] for i in te)
    assert D.split_train_val_test(names, lengths, seed=1) != (tr, va, te)
    with pytest.raises(ValueError, match="at least 3"):
        D.split_train_val_test(["a", "b"], [1, 2])
    tr, va, te = D.split_train_val_test(["a", "b", "c"], [90, 90, 95])
    assert te == [2] and len(va) == 1 and len(tr) == 1  # no split is left empty
