"""Results that are probably wrong are said: rig units, frame order, empty cameras, 0 people."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from roomcap.calibrate.camera import CameraRig
from roomcap.calibrate.checks import rig_warnings
from roomcap.capture.session import SessionLayout
from roomcap.core.errors import FormatError
from roomcap.keypoints.detections import Detections
from roomcap.pipeline.config import PipelineConfig
from roomcap.pipeline.discover import discover
from roomcap.pipeline.runner import process_session
from roomcap.pipeline.synth import make_session
from roomcap.synthetic.rigs import ring_rig
from roomcap.triangulate.stage import triangulate_session


def _scaled(rig: CameraRig, factor: float) -> CameraRig:
    return CameraRig(tuple(dataclasses.replace(c, t=c.t * factor) for c in rig.cameras))


def _run(root, stages=("triangulate", "track")):
    (src,) = discover([root])
    return process_session(src, None, PipelineConfig().replace(stages=stages))


def test_rig_in_millimetres_is_said():
    rig = ring_rig(4, radius_m=3.0)
    assert rig_warnings(rig) == []
    (w,) = rig_warnings(_scaled(rig, 1000.0))
    assert "millimetres" in w and "--scale-to-m 0.001" in w and "km" in w
    (w,) = rig_warnings(_scaled(rig, 1e-3))
    assert "mm apart" in w


def test_session_with_a_millimetre_rig_ends_with_warnings_not_silence(tmp_path):
    root = make_session(tmp_path / "s", n_people=2, duration_s=0.4)
    lay = SessionLayout(root)
    _scaled(CameraRig.load(lay.rig_toml), 1000.0).save(lay.rig_toml)  # translations now in mm
    res = _run(root)
    assert res.status == "ok" and res.people == 0
    text = " ".join(res.warnings)
    assert "millimetres" in text and "0 people" in text
    assert res.message.startswith("warning:")


def _shuffle_frames(path, how: str) -> None:
    d = Detections.load(path)
    order = np.arange(len(d.frame_index))
    fi = d.frame_index.copy()
    if how == "reversed":
        order = order[::-1]
        fi = fi[order]
    else:  # a frame number written twice
        fi[3] = fi[2]
    dataclasses.replace(
        d,
        frame_index=fi,
        t_ns=d.t_ns[order],
        xy_px=d.xy_px[order],
        score=d.score[order],
        boxes=d.boxes[order],
    ).save(path)


@pytest.mark.parametrize("how,word", [("reversed", "goes back to"), ("duplicated", "repeats")])
def test_frame_numbers_out_of_order_are_an_error_naming_camera_and_frame(tmp_path, how, word):
    root = make_session(tmp_path / "s", n_people=1, duration_s=0.4)
    lay = SessionLayout(root)
    _shuffle_frames(lay.detections("cam01"), how)
    with pytest.raises(FormatError, match=rf"camera 'cam01': frame_index is not strictly increasing.*{word}"):
        triangulate_session(root)
    res = _run(root)
    assert res.status == "failed" and "cam01" in res.message and word in res.message


def test_timestamps_that_go_backwards_are_an_error(tmp_path):
    root = make_session(tmp_path / "s", n_people=1, duration_s=0.4)
    lay = SessionLayout(root)
    d = Detections.load(lay.detections("cam02"))
    t = d.t_ns.copy()
    t[5] = t[1]
    dataclasses.replace(d, t_ns=t).save(lay.detections("cam02"))
    with pytest.raises(
        FormatError, match=r"camera 'cam02': timestamps go backwards at frame 5 .*after frame 4"
    ):
        triangulate_session(root)
    res = _run(root)  # the session fails saying so: no frame is dropped silently
    assert res.status == "failed" and "cam02" in res.message and "backwards at frame 5" in res.message


def test_empty_camera_and_unalignable_lengths_are_warned(tmp_path):
    root = make_session(tmp_path / "s", n_people=1, duration_s=0.8)
    lay = SessionLayout(root)
    d = Detections.load(lay.detections("cam00"))
    dataclasses.replace(d, xy_px=np.full_like(d.xy_px, np.nan), score=np.zeros_like(d.score)).save(
        lay.detections("cam00")
    )
    d = Detections.load(lay.detections("cam03"))
    n = len(d.frame_index) // 2
    dataclasses.replace(
        d,
        frame_index=d.frame_index[:n],
        t_ns=np.zeros(n, np.int64),
        xy_px=d.xy_px[:n],
        score=d.score[:n],
        boxes=d.boxes[:n],
    ).save(lay.detections("cam03"))
    for c in ("cam01", "cam02", "cam00"):  # no camera has timestamps
        d = Detections.load(lay.detections(c))
        dataclasses.replace(d, t_ns=np.zeros_like(d.t_ns)).save(lay.detections(c))
    res = _run(root)
    assert res.status == "ok" and res.people == 1
    text = " ".join(res.warnings)
    assert "camera 'cam00' has no detection" in text
    assert "cover different frames" in text and "cam03 0-" in text
