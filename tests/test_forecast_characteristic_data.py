"""The characteristic-pose commands' clip sources (``--data cmu`` / ``--data cmu-all``): the split of the
other forecasting commands, the benchmark's test files never in training, and both commands end to end."""

from __future__ import annotations

import json

import pytest
import torch

from roomcap.core.errors import InputError
from roomcap.forecast.lab import characteristic as C
from roomcap.forecast.lab.characteristic.cli import main
from roomcap.forecast.lab.characteristic.protocol import load_labelled
from roomcap.forecast.lab.clips import load_one_person_all

torch.set_num_threads(1)
TINY = ["hidden=16", "dim=16", "heads=2", "grid=8", "channels=4", "batch=4", "val_every=0"]


def test_unknown_data_source_is_a_clear_error():
    with pytest.raises(InputError, match="cmu-all"):
        load_labelled("cmu-everything")


def test_cmu_all_uses_the_split_of_the_other_forecasting_commands():
    from conftest import need_shared

    need_shared("data", "motion")
    old, full = load_labelled("cmu"), load_labelled("cmu-all")
    split = load_one_person_all(0)
    for part in ("train", "val", "test"):
        names = [it.name for it in getattr(full, part)]
        assert names == [c.name for c in getattr(split, part)]  # one person per clip, in the split's order
        # the cmu clips keep the split that the shipped checkpoint was trained and selected on
        assert {it.name for it in getattr(old, part)} <= set(names)
    used = {it.name for it in full.train + full.val}
    assert not any(n.startswith("cmu8_test_") for n in used)  # the benchmark's test files: test only
    assert any(it.name.startswith("cmu8_test_") for it in full.test)
    assert any(it.name.startswith("cmu8_train_") for it in full.train)
    assert len(C.segments(full.train, 10)) > 2 * len(C.segments(old.train, 10))  # labels computed for all


def test_train_and_eval_commands_on_cmu_all(tmp_path, capsys):
    from conftest import need_shared

    need_shared("data", "motion")
    ck = tmp_path / "c.pt"
    sets = ["steps=2", "det_steps=2", *TINY]
    assert main(["train", "--data", "cmu-all", "--out", str(ck), "--set", *sets, "--no-eval"]) == 0
    _, _, meta = C.load_checkpoint(ck, skeleton="body19")
    full = load_labelled("cmu-all", meta["fps"])
    assert meta["extra"]["data"] == "cmu-all"
    assert meta["extra"]["history"]["n_train_labels"] == len(C.segments(full.train, 10))
    out = tmp_path / "r.json"
    args = ["eval", "--checkpoint", str(ck), "--data", "cmu-all", "--split", "val", "--max-windows", "10"]
    assert main([*args, "--k", "2", "--no-refine", "--json", str(out)]) == 0
    res = json.loads(out.read_text())
    assert res["data"] == "cmu-all" and res["split"] == "val" and res["n_windows"] == 10
    assert res["n_labels"] == len(C.segments(full.val, 10))
    assert "CMU (cmu-all) val split" in capsys.readouterr().out
    with pytest.raises(SystemExit) as stop:  # argparse: not a source; the choices are named
        main([*args[:4], "--data", "nope"])
    assert stop.value.code == 2 and "cmu-all" in capsys.readouterr().err
