"""Decoders on synthetic outputs, and the OpenMMLab signatures (SimCC, RTMO, mmdeploy detector) end to end
through onnxruntime on tiny ONNX graphs built here (keypoints_tiny.py)."""

from __future__ import annotations

import numpy as np
import pytest
from keypoints_tiny import make_dets_model, make_rtmo_model, make_simcc_model

from roomcap.keypoints import decoders as D
from roomcap.keypoints.crops import crop_transform
from roomcap.keypoints.pipeline import KeypointPipeline, KeypointPipelineConfig
from roomcap.keypoints.registry import ModelError
from roomcap.keypoints.runtime import OnnxModel, RuntimeConfig


@pytest.fixture
def models(tmp_path, monkeypatch):
    monkeypatch.setenv("ROOMCAP_CACHE", str(tmp_path / "cache"))
    monkeypatch.setenv("ROOMCAP_MODELS", str(tmp_path))
    return tmp_path


def test_nms_keeps_best_of_overlapping_boxes():
    boxes = np.array([[0, 0, 10, 10], [1, 1, 11, 11], [20, 20, 30, 30]], float)
    keep = D.nms(boxes, np.array([0.5, 0.9, 0.7]), 0.45)
    assert keep.tolist() == [1, 2]


def test_yolox_grid_decode():
    size = (64, 32)  # w, h: grids 8x4, 4x2, 2x1 = 42 anchors
    raw = np.zeros((1, 42, 6), np.float32)
    raw[..., 4] = 0.01
    # anchor (gx=3, gy=1) at stride 8 is index 1*8+3 = 11: centre ((0.5+3)*8, (0.25+1)*8), size exp(1)*8
    raw[0, 11] = [0.5, 0.25, 1.0, 0.0, 0.9, 0.8]
    out = D.decode_yolox(raw, size, (8, 16, 32), 0, 0.3)
    assert len(out[0]) == 1
    cx, cy, w, h = 28.0, 10.0, np.e * 8, 8.0
    np.testing.assert_allclose(out[0][0], [cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2, 0.72], rtol=1e-5)
    with pytest.raises(ValueError, match="expected"):
        D.decode_yolox(raw[:, :40], size)


def test_blazepose_and_movenet_decoders():
    lm = np.zeros((2, 195), np.float32)
    lm.reshape(2, 39, 5)[:, :, :2] = [100.0, 50.0]
    lm.reshape(2, 39, 5)[1, :, 3:] = -10.0  # invisible, absent
    xy, sc, person, aux = D.decode_blazepose(lm, np.array([[5.0], [-5.0]]))
    assert aux.shape == (2, 6, 2)
    assert xy.shape == (2, 33, 2) and np.allclose(xy[0, 0], [100, 50])
    assert sc[0, 0] == pytest.approx(0.25) and sc[1, 0] < 1e-8
    assert person[0] > 0.99 and person[1] < 0.01
    mv = np.zeros((1, 1, 17, 3), np.float32)
    mv[0, 0, 3] = [0.5, 0.25, 0.7]  # (y, x, score)
    xy, sc = D.decode_movenet(mv, (192, 192))
    assert np.allclose(xy[0, 3], [48, 96]) and sc[0, 3] == pytest.approx(0.7)


def test_paf_grouping_separates_two_people():
    H, W = 40, 40
    heat = np.zeros((H, W, 18), np.float32)
    pafs = np.zeros((H, W, 38), np.float32)
    people = {0: (10, 5), 1: (30, 5)}  # neck x, top y
    for x, y0 in people.values():
        pts = {1: (x, y0), 2: (x - 4, y0 + 1), 8: (x - 2, y0 + 15), 9: (x - 2, y0 + 25)}
        for part, (px, py) in pts.items():
            heat[py, px, part] = 0.9
        for k, (a, b) in enumerate(D.OPENPOSE_LIMBS):
            if a in pts and b in pts:
                (ax, ay), (bx, by) = pts[a], pts[b]
                n = np.hypot(bx - ax, by - ay)
                for t in np.linspace(0, 1, 40):
                    pafs[
                        int(round(ay + t * (by - ay))), int(round(ax + t * (bx - ax))), 2 * k : 2 * k + 2
                    ] = [(bx - ax) / n, (by - ay) / n]
    peaks = D.find_peaks(heat, 0.1, sigma=0)
    xy, sc = D.group_paf(peaks, pafs)
    assert len(xy) == 2
    necks = sorted(xy[:, 1, 0].tolist())
    assert necks == pytest.approx([10, 30], abs=0.5)
    for p in range(2):  # each person's parts all come from one side
        side = xy[p, 1, 0] > 20
        assert ((xy[p, [2, 8, 9], 0] > 20) == side).all()


def test_simcc_top_down_through_tiny_onnx_graphs(models, rng):
    """Detector (mmdeploy dets) -> affine crop 192x256 -> SimCC; keypoints come back in image px."""
    kp_crop = np.stack([np.arange(17) * 10 + 5, np.arange(17) * 12 + 20], 1).astype(np.float32)  # crop px
    make_simcc_model(models, kp_crop)
    box_in = np.array([[100, 50, 300, 450, 0.9], [0, 0, 10, 10, 0.1]], np.float32)  # 640x640 input px
    make_dets_model(models, box_in, np.array([0, 0]))
    pipe = KeypointPipeline(
        KeypointPipelineConfig(
            model_set="tiny_det+tiny_simcc",
            skeleton="model",
            refine_passes=0,
            min_box_px=1,
            runtime=RuntimeConfig(dynamic_batch=True),
        )
    )
    assert pipe.pose.max_batch is None  # fixed batch 1 made dynamic
    img = rng.integers(0, 255, (960, 1280, 3), dtype=np.uint8)  # letterbox r = 0.5
    res = pipe([img, img[:480]])
    assert len(res[0].boxes) == 1  # the 0.1 box is below the threshold
    box_img = box_in[0, :4] / 0.5
    np.testing.assert_allclose(res[0].boxes[0, :4], box_img)
    M = crop_transform(box_img, (192, 256), 1.25)
    expect = (kp_crop - M[:, 2]) / M[0, 0]
    np.testing.assert_allclose(res[0].xy_px[0], expect, atol=1e-3)
    assert np.allclose(res[0].score, 0.9)
    # in body19 the derived neck is the mid-shoulder
    pipe19 = KeypointPipeline(
        KeypointPipelineConfig(model_set="tiny_det+tiny_simcc", refine_passes=0, min_box_px=1)
    )
    r19 = pipe19([img])[0]
    np.testing.assert_allclose(r19.xy_px[0, 18], 0.5 * (expect[5] + expect[6]), atol=1e-3)


def test_rtmo_one_stage_through_tiny_onnx_graph(models):
    dets = np.array([[10, 20, 110, 220, 0.9], [12, 22, 108, 218, 0.8], [300, 300, 400, 500, 0.2]], np.float32)
    kpts = np.zeros((3, 17, 3), np.float32)
    kpts[..., 0], kpts[..., 1], kpts[..., 2] = 50, 100, 0.8
    make_rtmo_model(models, dets, kpts)
    pipe = KeypointPipeline(KeypointPipelineConfig(model_set="tiny_rtmo", skeleton="model"))
    res = pipe([np.zeros((1280, 640, 3), np.uint8)])[0]  # portrait: r = 0.5
    assert len(res.boxes) == 1  # NMS merges the duplicate, the threshold drops the weak one
    np.testing.assert_allclose(res.boxes[0, :4], dets[0, :4] * 2)
    np.testing.assert_allclose(res.xy_px[0], np.tile([100.0, 200.0], (17, 1)))


def test_input_shape_not_matching_the_description_is_refused(models):
    make_simcc_model(models, np.zeros((17, 2)), name="wrong", graph_size_wh=(128, 128))
    with pytest.raises(ModelError, match=r"input shape \[1, 3, 128, 128\] does not match.*192x256"):
        OnnxModel("wrong", RuntimeConfig(model_dir=str(models)))


def test_movenet_multipose_decoder_reads_keypoints_then_box():
    from roomcap.keypoints.decoders import decode_movenet_multipose

    out = np.zeros((1, 6, 56), np.float32)
    k = np.zeros((17, 3), np.float32)
    k[:, 0], k[:, 1], k[:, 2] = 0.5, 0.25, 0.9  # y, x, score
    out[0, 0, :51] = k.ravel()
    out[0, 0, 51:56] = (0.1, 0.2, 0.9, 0.3, 0.8)  # ymin, xmin, ymax, xmax, score
    out[0, 1, 55] = 0.1  # below the threshold
    ((boxes, xy, sc),) = decode_movenet_multipose(out, (256, 128), 0.2)
    np.testing.assert_allclose(boxes, [[0.2 * 256, 0.1 * 128, 0.3 * 256, 0.9 * 128, 0.8]], rtol=1e-6)
    np.testing.assert_allclose(xy[0, 0], [64.0, 64.0])
    assert xy.shape == (1, 17, 2) and np.allclose(sc, 0.9)
    with pytest.raises(ValueError, match="56"):
        decode_movenet_multipose(np.zeros((1, 6, 50)), (256, 256))
