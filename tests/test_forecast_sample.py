"""``forecast sample`` on what users give it: session folders, other frame rates, short tracks, checkpoints
of other kinds and versions; and the pictures it draws."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from roomcap.core.errors import FormatError
from roomcap.forecast.cli import main
from roomcap.forecast.lab import data as D
from roomcap.forecast.lab.toy import walker
from roomcap.forecast.runtime import checkpoint as C
from roomcap.forecast.runtime.registry import build_model, config_from_dict
from roomcap.keypoints.skeletons import get_skeleton
from roomcap.track.trackfile import TrackFile

torch.set_num_threads(1)


def _track(path, T_=90, fps=25.0):
    """Two walkers at ``fps`` (the toy walker's motion at 25 Hz, resampled), written as a track file."""
    sk = get_skeleton("body19")
    xyz25 = np.stack([walker(int(T_ * 25 / fps) + 2), walker(int(T_ * 25 / fps) + 2, start=(2, 1))], 1)
    xyz = D.Clip("w", xyz25, 25.0).resampled(fps).xyz_m[:T_]
    T_ = len(xyz)
    tf = TrackFile(
        fps=fps,
        frame_index=np.arange(T_),
        t_ns=(np.arange(T_) * 1e9 / fps).astype(np.int64),
        track_id=[3, 8],
        joint_names=sk.joint_names,
        parents=np.asarray(sk.parents),
        xyz_m=xyz,
        confidence=np.ones(xyz.shape[:3]),
        std_m=np.full(xyz.shape[:3], 0.02),
        flags=np.ones(xyz.shape[:3], np.uint8),
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    tf.save(path)
    return path


@pytest.fixture(scope="module")
def gru(tmp_path_factory):
    """An untrained GRU checkpoint (n_obs 20 frames = 0.8 s at 25 Hz): what it forecasts does not matter."""
    torch.manual_seed(0)
    cfg = config_from_dict("gru", {"hidden": 8, "n_obs": 20, "n_pred": 10})
    path = tmp_path_factory.mktemp("ck") / "gru.pt"
    C.save_checkpoint(path, build_model("gru", cfg, 19), "gru", cfg)
    return path


def _sample(gru, tracks, out, *extra):
    return main(["sample", "--checkpoint", str(gru), "--tracks", str(tracks), "--out", str(out), *extra])


def test_a_session_folder_is_read_as_its_track_or_live_track(gru, tmp_path, capsys):
    _track(tmp_path / "S1" / "track" / "tracks.npz")
    assert _sample(gru, tmp_path / "S1", tmp_path / "a.npz", "--no-pictures") == 0
    assert np.load(tmp_path / "a.npz")["xyz_m"].shape == (1, 25, 2, 19, 3)
    live = _track(tmp_path / "S2" / "track" / "live.npz", T_=60)  # only the live track (capture-run --live)
    assert _sample(gru, tmp_path / "S2", tmp_path / "b.npz", "--no-pictures") == 0
    assert np.allclose(np.load(tmp_path / "b.npz")["obs_xyz_m"][-1], TrackFile.load(live).xyz_m[-1])
    (tmp_path / "S3").mkdir()
    assert _sample(gru, tmp_path / "S3", tmp_path / "c.npz") == 2
    assert "has no track file (looked for track/tracks.npz" in capsys.readouterr().err
    assert not (tmp_path / "c.npz").exists()


def test_another_frame_rate_is_resampled_and_said(gru, tmp_path, capsys):
    """A 50 Hz track is forecast at the model's 25 Hz, as the same track at 25 Hz is."""
    _track(tmp_path / "t50.npz", T_=120, fps=50.0)
    _track(tmp_path / "t25.npz", T_=60, fps=25.0)
    assert _sample(gru, tmp_path / "t50.npz", tmp_path / "f50.npz", "--no-pictures") == 0
    out = capsys.readouterr().out
    assert "is at 50 Hz and the model (gru) at 25 Hz: the track was resampled to 25 Hz" in out, out
    assert _sample(gru, tmp_path / "t25.npz", tmp_path / "f25.npz", "--no-pictures") == 0
    assert "resampled" not in capsys.readouterr().out
    a, b = np.load(tmp_path / "f50.npz"), np.load(tmp_path / "f25.npz")
    assert float(a["fps"]) == 25.0 and float(a["track_fps"]) == 50.0 and a["xyz_m"].shape == b["xyz_m"].shape
    assert np.abs(a["obs_xyz_m"] - b["obs_xyz_m"]).max() < 0.02  # the last 0.8 s, resampled vs native
    assert np.abs(a["xyz_m"] - b["xyz_m"]).max() < 0.05


def test_a_track_shorter_than_the_observation_says_how_long_it_must_be(gru, tmp_path, capsys):
    _track(tmp_path / "short.npz", T_=30, fps=60.0)  # 0.5 s; the model observes 0.8 s
    assert _sample(gru, tmp_path / "short.npz", tmp_path / "f.npz") == 2
    err = capsys.readouterr().err
    assert "holds 13 frames (0.52 s at 25 Hz, resampled from its 60 Hz)" in err, err
    assert "must be at least 0.8 s long (20 frames at 25 Hz)" in err and "--obs-s 0.52 or less" in err
    assert not (tmp_path / "f.npz").exists()
    assert _sample(gru, tmp_path / "short.npz", tmp_path / "f.npz", "--obs-s", "0.52", "--no-pictures") == 0
    assert np.load(tmp_path / "f.npz")["obs_xyz_m"].shape[0] == 13
    assert _sample(gru, tmp_path / "short.npz", tmp_path / "g.npz", "--start-s", "9") == 2
    assert "--start-s 9 is outside" in capsys.readouterr().err


def test_pictures_one_per_person_with_the_truth_after_start(gru, tmp_path, capsys):
    tracks = _track(tmp_path / "t.npz", T_=90)
    tf = TrackFile.load(tracks)
    tf.xyz_m[-5:, 1] = np.nan  # track 8 gone at the end: nothing forecast, no picture
    tf.save(tracks)
    assert _sample(gru, tracks, tmp_path / "out" / "fc.npz", "--horizon-s", "0.8") == 0
    assert "picture: " in capsys.readouterr().out
    assert [p.name for p in sorted((tmp_path / "out").glob("*.png"))] == ["fc_track3.png"]
    assert (tmp_path / "out" / "fc_track3.png").stat().st_size > 20_000
    f = np.load(tmp_path / "out" / "fc.npz")
    assert np.isnan(f["truth_xyz_m"]).all()  # forecast from the last frame: no truth
    assert _sample(gru, tracks, tmp_path / "fc2.npz", "--start-s", "2.0", "--horizon-s", "1.0") == 0
    f = np.load(tmp_path / "fc2.npz")
    assert np.allclose(f["truth_xyz_m"][:25, 0], tf.xyz_m[51:76, 0], atol=1e-6)  # frames after 2.0 s
    assert np.allclose(f["obs_xyz_m"][-1, 0], tf.xyz_m[50, 0], atol=1e-6)
    assert {p.name for p in tmp_path.glob("fc2_track*.png")} == {"fc2_track3.png", "fc2_track8.png"}


# ----------------------------------------------------------------------------- checkpoints of other kinds


def test_every_family_is_written_and_read_by_the_one_format():
    """The lab's families name their registry family; the one reader refuses a file of another family with
    what it is."""
    from roomcap.forecast.lab import benchmark_cmu8, benchmark_cmu8_angle, benchmark_cmu8_angle_intention
    from roomcap.forecast.lab.behaviour import model as behaviour_model
    from roomcap.forecast.lab.behaviour import quality
    from roomcap.forecast.lab.characteristic import model as characteristic_model
    from roomcap.forecast.runtime.registry import FAMILIES, MODELS

    owners = {benchmark_cmu8.FAMILY, benchmark_cmu8_angle.FAMILY, characteristic_model.FAMILY}
    owners |= {behaviour_model.FAMILY, quality.FAMILY, benchmark_cmu8_angle_intention.FAMILY, *MODELS}
    assert set(FAMILIES) == owners


def _v1(state: dict) -> dict:
    """A GRU checkpoint of the first format (forecast-checkpoint/1), as roomcap wrote it before the one."""
    cfg = config_from_dict("gru", {"hidden": 8, "n_obs": 20, "n_pred": 10})
    return {
        "schema": "forecast-checkpoint/1",
        "kind": "gru",
        "config": __import__("dataclasses").asdict(cfg),
        "skeleton": "body19",
        "joint_names": list(get_skeleton("body19").joint_names),
        "fps": 25.0,
        "normalisation": C.NORMALISATION,
        "state_dict": state,
        "extra": {"train_clips": ["a"], "val_clips": ["b"], "test_clips": ["c"], "command": "forecast train"},
    }


def test_an_older_schema_is_upgraded_on_read_and_converted(gru, tmp_path, caplog, capsys):
    model, _ = C.load_checkpoint(gru)
    torch.save(_v1(model.state_dict()), tmp_path / "old.pt")
    with caplog.at_level("WARNING"):
        old, meta = C.load_checkpoint(tmp_path / "old.pt")
    assert "upgraded on read" in caplog.text and "forecast models --convert" in caplog.text
    assert meta["model"] == "gru" and meta["card"]["command"] == "forecast train"
    assert meta["upgraded_from"] == "forecast-checkpoint/1"
    assert all(
        torch.equal(a, b) for a, b in zip(old.state_dict().values(), model.state_dict().values(), strict=True)
    )
    assert main(["models", "--convert", str(tmp_path / "old.pt"), str(tmp_path / "new.pt")]) == 0
    assert "'forecast-checkpoint/1' -> 'forecast-checkpoint/2'" in capsys.readouterr().out
    blob = torch.load(tmp_path / "new.pt", weights_only=True)
    assert blob["schema"] == C.SCHEMA and set(blob["weights"]) == {"model"} and blob["card"]["split"]
    assert main(["models", "--convert", str(tmp_path / "missing.pt"), str(tmp_path / "x.pt")]) == 2


@pytest.mark.parametrize(
    ("blob", "words"),
    [
        ({"schema": "forecast-checkpoint/2", "model": "characteristic"}, "characteristic-3D-pose"),
        ({"schema": "forecast-checkpoint/2", "model": "cmu8_dct_mlp"}, "--protocol cmu8"),
        ({"schema": "forecast-checkpoint/2", "model": "behaviour"}, "forecast behaviour sample"),
        (
            {"schema": "forecast-checkpoint/2", "model": "transformer"},
            "model 'transformer', which this roomcap",
        ),
        ({"schema": "forecast-checkpoint/0", "kind": "gru"}, "which roomcap does not know (this version"),
        ({"w": torch.zeros(2), "b": torch.zeros(1)}, "bare PyTorch state dict (2 tensors"),
        ({"schema": "someone-else/3"}, "which roomcap does not know"),
    ],
)
def test_a_checkpoint_of_another_kind_is_named(tmp_path, blob, words):
    torch.save(blob, tmp_path / "x.pt")
    with pytest.raises(FormatError) as e:
        C.load_checkpoint(tmp_path / "x.pt")
    assert words in str(e.value) and "forecast train --model gru" in str(e.value)
    assert "\n" not in str(e.value)


def test_an_unknown_model_or_config_says_what_to_do(gru, tmp_path, capsys):
    blob = torch.load(gru, weights_only=True)
    torch.save({**blob, "model": "transformer"}, tmp_path / "t.pt")
    with pytest.raises(FormatError, match="model 'transformer', which this roomcap version does not know"):
        C.load_checkpoint(tmp_path / "t.pt")
    torch.save({**blob, "config": {**blob["config"], "heads": 4}}, tmp_path / "c.pt")
    with pytest.raises(FormatError, match="gru config does not fit this roomcap version") as e:
        C.load_checkpoint(tmp_path / "c.pt")
    assert "heads" in str(e.value) and "forecast train --model gru" in str(e.value)
    _track(tmp_path / "t.npz")
    assert main(["sample", "--checkpoint", str(tmp_path / "t.pt"), "--tracks", str(tmp_path / "t.npz"),
                 "--out", str(tmp_path / "f.npz")]) == 2  # fmt: skip
    assert "does not know" in capsys.readouterr().err


def test_pictures_of_a_stochastic_forecast_draw_the_spread(tmp_path):
    from roomcap.forecast.runtime.sample_plot import plot_forecasts

    S, H, K, J = 8, 25, 2, 19
    rng = np.random.default_rng(0)
    obs = np.stack([walker(20), walker(20, start=(2, 1))], 1)
    fut = np.repeat(np.stack([walker(45), walker(45, start=(2, 1))], 1)[None, 20:], S, 0)
    fut = fut + rng.normal(0, 0.05, (S, 1, K, 1, 3)) * np.arange(1, H + 1)[None, :, None, None, None] / H
    fc = {
        "xyz_m": fut.astype(np.float32),
        "obs_xyz_m": obs,
        "truth_xyz_m": np.full((H, K, J, 3), np.nan),
        "track_id": np.array([0, 5]),
        "fps": 25.0,
        "track_fps": 60.0,
        "joint_names": np.asarray(get_skeleton("body19").joint_names),
        "model": "intention",
    }
    paths = plot_forecasts(fc, tmp_path / "fc.npz", title="toy")
    assert [p.name for p in paths] == ["fc_track0.png", "fc_track5.png"] and all(p.exists() for p in paths)


def test_the_cmu8_reader_names_a_checkpoint_of_another_kind(gru):
    from roomcap.forecast.lab.benchmark_cmu8 import load_mlp

    with pytest.raises(FormatError, match=r"a 'gru' checkpoint, not 'cmu8_dct_mlp': seq2seq GRU"):
        load_mlp(gru)


def test_forecast_models_lists_the_cards(gru, tmp_path, capsys):
    import json

    from roomcap.forecast.runtime.cards import cards
    from roomcap.forecast.runtime.preview import CHECKPOINT_DIR, DEFAULT_CHECKPOINT

    assert main(["models"]) == 0
    out = capsys.readouterr().out
    shipped = sorted(p.name for p in CHECKPOINT_DIR.glob("*.pt"))
    assert [ln.split()[0] for ln in out.splitlines() if ln and not ln.startswith(" ")] == shipped
    default = next(ln for ln in out.splitlines() if ln.startswith(DEFAULT_CHECKPOINT.name))
    assert "the default of forecast sample" in default
    folder = tmp_path / "cks"
    folder.mkdir()
    (folder / "a.pt").write_bytes((gru).read_bytes())
    torch.save({"w": torch.zeros(3)}, folder / "b.pt")
    (folder / "c.pt").write_bytes(b"junk")
    assert main(["models", "--folder", str(folder), "--json"]) == 0
    cs = json.loads(capsys.readouterr().out)
    assert [c["file"] for c in cs] == ["a.pt", "b.pt", "c.pt"]
    assert cs[0]["model"] == "gru" and cs[0]["observes"] == "20 frames (0.8 s)"
    assert "bare PyTorch state dict" in cs[1]["what"] and "not a readable checkpoint" in cs[2]["what"]
    for c in cards(CHECKPOINT_DIR):  # every shipped file is of the one format, its card says how it was made
        assert c["schema"] == C.SCHEMA and {"data", "selection", "scores", "command"} <= set(c), c["file"]
    assert main(["models", "--folder", str(tmp_path / "none")]) == 2
    assert "is not a folder of checkpoints" in capsys.readouterr().err
