"""The checkpoints trained on every one-person CMU clip (``--data cmu-all``) and on the real two-person takes
(``--data two-person``): small, loadable with weights only, never trained or selected on a test clip (the
8-action benchmark's test files, the held-out salsa takes), picked on validation NDMS."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from roomcap.forecast.lab import train as T
from roomcap.forecast.lab.toy import walker
from roomcap.forecast.runtime.predict import forecast_world
from roomcap.forecast.runtime.preview import CHECKPOINT_DIR as ROOT

SHIPPED = {
    "gru_cmuall.pt": "gru",
    "intention_cmuall.pt": "intention",
    "social_diffusion_salsa.pt": "social_diffusion",
    "social_diffusion_1pass_cmuall.pt": "social_diffusion",
}
# picked by the recipe's own criterion; the others by NDMS 2-4 s
SELECTED_BY = {"gru_cmuall.pt": "mpjpe_0_1"}
# the shipped files: the best of each family on validation, and those that reproduce a published table
KEPT = {
    *SHIPPED,
    "characteristic_cmuall.pt",
    "cmu8_dct_mlp_ens.pt",
    "cmu8_angle_dct_mlp.pt",
    "behaviour_cmu.pt",
    "behaviour_quality_cmu.pt",
    "behaviour_stations_cmu.pt",
    "behaviour_quality_stations_cmu.pt",
}


def test_the_shipped_checkpoints_are_the_kept_ones():
    """Retired files stay retired (and a new file comes with its test): the folder holds exactly these."""
    assert {p.name for p in ROOT.glob("*.pt")} == KEPT


@pytest.mark.parametrize("name", sorted(SHIPPED))
def test_checkpoint_small_clean_split_and_selected_on_validation(name):
    ck = ROOT / name
    if not ck.exists():
        pytest.skip(f"{name} is not shipped")
    assert ck.stat().st_size < 2_000_000
    blob = torch.load(ck, map_location="cpu", weights_only=True)  # plain tensors and builtins only
    assert blob["model"] == SHIPPED[name]
    model, meta = T.load_checkpoint(ck, skeleton="body19")
    extra = meta["extra"]
    used = set(extra["train_clips"]) | set(extra["val_clips"])
    assert used and not used & set(extra["test_clips"])
    assert not any(n.startswith("cmu8_test_") for n in used)  # the benchmark's test files: test only
    assert extra["val_best"]["select"] == SELECTED_BY.get(name, "ndms_2_4")  # picked on the validation split
    if name == "social_diffusion_salsa.pt":
        assert any("+" in n for n in extra["test_clips"])  # held-out salsa takes
    else:
        assert any(
            n.startswith("cmu8_train_") for n in extra["train_clips"]
        )  # trained on all one-person data
    if SHIPPED[name] == "social_diffusion":
        scene = np.stack([walker(32), walker(32, start=(1.2, 0), heading_rad=2.0)], 1)[None]
        y = forecast_world(model, scene, None, 50, 1)
    else:
        y = forecast_world(model, walker(50)[None, :, None], None, 50, 2)
    assert np.isfinite(y).all()


def test_characteristic_checkpoint_on_all_one_person_data():
    """``characteristic_cmuall.pt`` (``forecast characteristic train --data cmu-all``): small, weights only,
    trained on the cmu-all train split (the benchmark's test files never in it), selected on validation."""
    from roomcap.forecast.lab import characteristic as C

    ck = ROOT / "characteristic_cmuall.pt"
    if not ck.exists():
        pytest.skip("characteristic_cmuall.pt is not shipped")
    assert ck.stat().st_size < 2_000_000
    blob = torch.load(ck, map_location="cpu", weights_only=True)  # plain tensors and builtins only
    assert blob["model"] == "characteristic"
    net, _, meta = C.load_checkpoint(ck, skeleton="body19")
    extra = meta["extra"]
    assert extra["data"] == "cmu-all" and "--data cmu-all" in extra["command"]
    assert extra["history"]["heatmap"]["val_best"]["mpjpe_best_of_k"] > 0  # picked on the validation split
    obs = torch.from_numpy(walker(10)[None].astype(np.float32))
    obs = obs - obs[:, -1:, 11:13].mean(2, keepdim=True)
    y = net.sample(obs, 3, refine=False, generator=torch.Generator().manual_seed(0))
    assert y.shape == (1, 3, 19, 3) and torch.isfinite(y).all()
    from conftest import need_shared

    need_shared("data", "motion")
    full = C.load_labelled("cmu-all", meta["fps"])
    assert extra["history"]["n_train_labels"] == len(C.segments(full.train, meta["config"].n_obs))
    assert not any(it.name.startswith("cmu8_test_") for it in full.train + full.val)


def test_rescore_writes_todays_validation_scores_into_the_card(tmp_path, capsys):
    """``forecast models --rescore CK``: the model scored on its own validation clips as it forecasts today;
    the card's scores replaced, the ones before kept, the weights unchanged; the shipped card is current."""
    from conftest import need_shared

    from roomcap.forecast.cli import main

    need_shared("data", "motion")
    src = ROOT / "gru_cmuall.pt"
    ck = tmp_path / src.name
    ck.write_bytes(src.read_bytes())
    before = torch.load(src, map_location="cpu", weights_only=False)
    before["card"]["scores"] = {"split": "validation", "ndms_2_4": 0.5, "mpjpe_0_1_m": 9.0}  # a stale card
    torch.save(before, ck)
    assert main(["models", "--rescore", str(ck)]) == 0
    after = torch.load(ck, map_location="cpu", weights_only=False)
    assert after["card"]["scores_before"]["mpjpe_0_1_m"] == 9.0
    new = after["card"]["scores"]
    assert 0.05 < new["mpjpe_0_1_m"] < 1.0 and 0.0 < new["ndms_2_4"] < 0.5
    shipped = torch.load(src, map_location="cpu", weights_only=False)["card"]["scores"]
    assert new["mpjpe_0_1_m"] == pytest.approx(
        shipped["mpjpe_0_1_m"], rel=1e-3
    )  # the shipped card is today's
    for k, v in before["weights"]["model"].items():
        assert torch.equal(v, after["weights"]["model"][k])
    assert "gru_cmuall.pt: validation" in capsys.readouterr().out
    wrong = tmp_path / "cmu8.pt"
    wrong.write_bytes((ROOT / "cmu8_dct_mlp_ens.pt").read_bytes())
    assert main(["models", "--rescore", str(wrong)]) == 2


def test_the_runtime_part_stays_small():
    """Issue 40's bound: what loading a checkpoint and forecasting a track needs (``forecast/runtime``) is at
    most 2,500 lines in all (``bench/arch_counts.py`` counts the same)."""
    import roomcap.forecast.runtime as runtime

    files = sorted(Path(runtime.__file__).parent.rglob("*.py"))
    n = sum(len(f.read_text(encoding="utf-8").splitlines()) for f in files)
    assert 1000 < n <= 2500, f"forecast/runtime holds {n} lines in {len(files)} files"
