"""Hand keypoints per view (keypoints.hand_model): the forearm crop's geometry, the landmarks mapped back to
the image, the palm detector's anchors and decoding, the hands presets, a missing hand model named, the
back-off on wrists without a hand (stand-in models), and the hands preset on a real frame of the Pose2Sim
single-person demo."""

from __future__ import annotations

import shutil

import cv2
import numpy as np
import pytest
from conftest import need_shared

from roomcap.keypoints import registry
from roomcap.keypoints.crops import apply_inverse
from roomcap.keypoints.hand_model import (
    backoff,
    decode_hand_landmarks,
    decode_palms,
    forearm_crop,
    landmarks_roi,
    palm_anchors,
    palm_hand_roi,
    square_transform,
    up_angle,
)
from roomcap.keypoints.presets import preset_config, resolve_preset
from roomcap.keypoints.registry import ModelError
from roomcap.keypoints.skeletons import HAND_LEFT, HAND_RIGHT, get_skeleton, whole_body


def to_crop(M: np.ndarray, p) -> np.ndarray:
    return M[:, :2] @ np.asarray(p, float) + M[:, 2]


@pytest.mark.parametrize("deg", [0.0, 30.0, 90.0, 135.0, 180.0, -60.0, -170.0])
def test_forearm_crop_turns_the_forearm_up(deg):
    a = np.deg2rad(deg)
    direction = np.array([np.sin(a), -np.cos(a)])  # elbow -> wrist, clockwise from the image's up
    elbow = np.array([600.0, 900.0])
    wrist = elbow + 120.0 * direction
    M = forearm_crop(elbow, wrist, 120.0, 224, extend=0.4, scale=1.5)
    e, w = to_crop(M, elbow), to_crop(M, wrist)
    # in the crop the forearm is vertical, the wrist above the elbow (the fingers point up)
    assert abs(e[0] - w[0]) < 1e-6 and e[1] > w[1]
    # the crop's centre is 0.4 forearm beyond the wrist; its side 1.5 forearm
    np.testing.assert_allclose(to_crop(M, wrist + 0.4 * (wrist - elbow)), [112.0, 112.0], atol=1e-9)
    np.testing.assert_allclose(np.sqrt(abs(np.linalg.det(M[:, :2]))), 224 / 180.0)
    # the crop's up axis is the forearm's direction in the image
    up_img = apply_inverse(M[None], np.array([[[112.0, 0.0], [112.0, 112.0]]]))[0]
    v = up_img[0] - up_img[1]
    np.testing.assert_allclose(v / np.linalg.norm(v), direction, atol=1e-9)
    assert up_angle(direction) == pytest.approx(np.arctan2(np.sin(a), np.cos(a)))


def test_landmarks_map_back_to_image_pixels():
    # forearm pointing right: wrist (300, 400), elbow (200, 400) -> crop centre (340, 400), side 150 px,
    # crop up = image +x. A landmark at model output (x, y) = corner coordinates: pixel centre x - 0.5.
    M = forearm_crop(np.array([200.0, 400.0]), np.array([300.0, 400.0]), 100.0, 224, 0.4, 1.5)
    s = 224 / 150.0
    lm = np.zeros((1, 63), np.float32)
    lm[0, 0:2] = (112.5, 112.5 + 30 * s)  # 30 image px below the centre in the crop = 30 px towards the elbow
    lm[0, 3:5] = (112.5 + 15 * s, 112.5 - 45 * s)  # right of the crop's axis = image +y, up = image +x
    xy, pres = decode_hand_landmarks(lm, np.array([[0.8]]))
    img = apply_inverse(M[None], xy.astype(np.float64))[0]
    np.testing.assert_allclose(img[0], [310.0, 400.0], atol=1e-4)
    np.testing.assert_allclose(img[1], [385.0, 415.0], atol=1e-4)
    assert pres.tolist() == pytest.approx([0.8])
    with pytest.raises(ValueError, match="63"):
        decode_hand_landmarks(np.zeros((1, 42)), np.zeros((1, 1)))


def test_palm_anchors_follow_mediapipe_ssd_layout():
    A = palm_anchors(192, (8, 16, 16, 16))
    assert A.shape == (2016, 2)  # 24^2 x 2 + 12^2 x 6
    np.testing.assert_allclose(A[0], [4, 4])
    np.testing.assert_allclose(A[1], [4, 4])  # 2 anchors per cell at stride 8
    np.testing.assert_allclose(A[2], [12, 4])  # then the next column
    np.testing.assert_allclose(A[48], [4, 12])  # row 1 of the 24 x 24 map
    np.testing.assert_allclose(A[1152], [8, 8])  # the stride-16 layers: 6 anchors per cell
    np.testing.assert_allclose(A[1157], [8, 8])
    np.testing.assert_allclose(A[1158], [24, 8])
    np.testing.assert_allclose(A[-1], [184, 184])


def test_palm_decode_on_a_synthetic_output():
    A = palm_anchors()
    raw = np.zeros((2016, 18), np.float32)
    logits = np.full((2016, 1), -10.0, np.float32)
    k = 1152 + 6 * (3 * 12 + 5)  # stride 16, row 3, column 5: centre (88, 56)
    np.testing.assert_allclose(A[k], [88, 56])
    raw[k, :4] = (3.0, -2.0, 30.0, 28.0)
    raw[k, 4:] = np.arange(14, dtype=np.float32)
    logits[k] = 3.0
    raw[k + 1, :4] = (4.0, -2.0, 30.0, 28.0)  # the same palm from the cell's next anchor, weaker: suppressed
    logits[k + 1] = 1.0
    far = 100  # stride 8, row 2, column 2: centre (20, 20), a second palm, weaker than the first
    raw[far, :4] = (0.0, 0.0, 20.0, 20.0)
    logits[far] = 0.5
    palms = decode_palms(raw, logits, A, score_thr=0.5, nms_iou=0.3)
    assert len(palms) == 2
    (s0, b0, kp0), (s1, b1, _) = palms
    assert s0 == pytest.approx(1 / (1 + np.exp(-3.0))) and s1 == pytest.approx(1 / (1 + np.exp(-0.5)))
    np.testing.assert_allclose(b0, [91, 54, 30, 28])
    np.testing.assert_allclose(kp0[0], [88, 57])
    np.testing.assert_allclose(kp0[6], [88 + 12, 56 + 13])
    np.testing.assert_allclose(b1, [20, 20, 20, 20])
    assert decode_palms(raw, logits, A, score_thr=0.99, nms_iou=0.3) == []


def test_palm_to_hand_roi():
    # fingers up: wrist keypoint below the middle finger's base; the ROI moves half the box up, side x 2.6
    kp = np.zeros((7, 2))
    kp[0], kp[2] = (100, 110), (100, 80)
    c, side, a = palm_hand_roi(np.array([100.0, 95.0, 20.0, 20.0]), kp)
    np.testing.assert_allclose(c, [100, 85])
    assert a == pytest.approx(0.0)
    assert side == pytest.approx(52.0)
    # fingers pointing left: the ROI moves left and the crop turns them up
    kp[0], kp[2] = (110, 100), (80, 100)
    c, side, a = palm_hand_roi(np.array([95.0, 100.0, 20.0, 24.0]), kp)
    np.testing.assert_allclose(c, [83, 100], atol=1e-9)
    M = square_transform(c, side, 224, a)
    assert to_crop(M, kp[2])[1] < to_crop(M, kp[0])[1] - 40  # the finger base above the wrist in the crop


def test_hands_presets_resolve():
    default = preset_config()
    assert default.hands == "" and default.palm == ""  # hands off by default
    h = resolve_preset("hands")
    assert h.config.hands.startswith("hand_landmark_") and h.config.palm == "palm_detection_full"
    assert h.config.model_set == preset_config("balanced").model_set
    assert h.config.hand_retry_every > 1 and preset_config("feet_hands").hand_retry_every > 1  # back-off on
    fh = preset_config("feet_hands")
    assert fh.model_set == preset_config("feet").model_set and fh.skeleton == "model" and fh.hands
    # the 3D stages' whole-body layout takes the hands of a <layout>_hands detections file
    wb = whole_body(["body19_hands"]).joint_names
    assert set(HAND_LEFT + HAND_RIGHT) <= set(wb)
    for name in ("hand_landmark_full", "hand_landmark_lite", "palm_detection_full"):
        spec = registry.get_spec(name)
        assert spec.role in ("hand", "palm") and spec.sha256


def test_missing_hand_model_is_named_with_where_it_is_looked_for(tmp_path, monkeypatch, capsys):
    shared = need_shared("models")
    from roomcap.keypoints.cli import main
    from roomcap.keypoints.pipeline import KeypointPipeline
    from roomcap.keypoints.runtime import RuntimeConfig

    body = tmp_path / "body_only"
    body.mkdir()
    for f in ("yolox_nano_416x416.onnx", "movenet_lightning_s16.onnx"):
        shutil.copy(shared / f, body / f)
    monkeypatch.setenv("ROOMCAP_CACHE", str(tmp_path / "cache"))
    monkeypatch.setattr(registry, "shared_models_dir", lambda: tmp_path / "noshared")
    monkeypatch.delenv("ROOMCAP_MODELS", raising=False)
    with pytest.raises(ModelError) as e:
        KeypointPipeline(preset_config("hands", runtime=RuntimeConfig(model_dir=str(body))))
    msg = str(e.value)
    assert "hand_landmark_lite.onnx not found in" in msg and str(body) in msg and "\n" not in msg
    video = tmp_path / "v.avi"
    w = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 10, (64, 64))
    for _ in range(2):
        w.write(np.zeros((64, 64, 3), np.uint8))
    w.release()
    argv = ["--model-dir", str(body), "run", "--preset", "hands", "--out", str(tmp_path / "o"), str(video)]
    capsys.readouterr()
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "hand_landmark_lite.onnx not found in" in err[0], err


@pytest.fixture(scope="module")
def demo_frames():
    need_shared("models")
    d = need_shared("data", "pose2sim", "demo-wheel-0.10.49", "Demo_SinglePerson", "videos")
    out = []
    for c in ("cam01", "cam02", "cam03", "cam04"):
        cap = cv2.VideoCapture(str(d / f"{c}.mp4"))
        cap.set(cv2.CAP_PROP_POS_FRAMES, 30)
        ok, img = cap.read()
        assert ok
        out.append(img)
    return out


def test_hands_preset_finds_the_persons_hands_on_a_real_frame(demo_frames):
    from roomcap.keypoints.pipeline import KeypointPipeline
    from roomcap.keypoints.runtime import RuntimeConfig

    pipe = KeypointPipeline(preset_config("hands", runtime=RuntimeConfig(threads=1)))
    assert pipe.skeleton == "body19_hands" and "hand_landmark_" in pipe.model_id
    res = pipe(demo_frames)
    sk = get_skeleton(pipe.skeleton)
    found = 0
    for r in res:
        assert r.xy_px.shape[1] == sk.n_joints
        p = int(np.argmax(r.boxes[:, 4] * (r.boxes[:, 3] - r.boxes[:, 1])))  # the participant
        for side, names in (("left", HAND_LEFT), ("right", HAND_RIGHT)):
            idx = [sk.index(n) for n in names]
            if (r.score[p, idx] <= 0).all():
                continue
            assert np.isfinite(r.xy_px[p, idx]).all()
            # the hand hangs on the body's wrist of its side: its root within a forearm of that wrist
            w, e = r.xy_px[p, sk.index(f"{side}_wrist")], r.xy_px[p, sk.index(f"{side}_elbow")]
            assert np.linalg.norm(r.xy_px[p, idx[0]] - w) < max(np.linalg.norm(w - e), 40.0)
            found += 1
    assert found >= 4  # of 8 hand views (4 cameras x 2 hands); 5 found when this was written
    assert pipe.hands.n_crops >= 8
    # an image without anyone: the hands layout, no people
    empty = pipe([np.zeros((240, 320, 3), np.uint8)])[0]
    assert empty.xy_px.shape == (0, sk.n_joints, 2) and empty.score.shape == (0, sk.n_joints)


def test_palm_detector_finds_a_real_hand(demo_frames):
    from roomcap.keypoints.crops import to_tensor
    from roomcap.keypoints.runtime import OnnxModel, RuntimeConfig

    palm = OnnxModel("palm_detection_full", RuntimeConfig(threads=1))
    wrist = np.array([375.0, 990.0])  # cam04's left wrist at frame 30 (the hand hangs down from it)
    M = square_transform(wrist, 250.0, 192)
    crop = cv2.warpAffine(demo_frames[3], M, (192, 192))
    outs = palm.run(to_tensor(crop[None], palm.spec))
    palms = decode_palms(outs[0][0], outs[1][0], palm_anchors(), 0.5, 0.3)
    assert palms
    _, box, kp = palms[0]
    kp_img = apply_inverse(M[None], kp[None])[0]
    assert np.linalg.norm(kp_img[0] - wrist) < 40  # the palm's wrist keypoint on the body's wrist
    assert kp_img[2][1] > kp_img[0][1]  # fingers down: the middle finger's base below the wrist


def test_landmarks_roi_tracks_the_hand():
    # a hand pointing right: wrist at (100, 200), finger bases 40 px to its right, spread over 30 px
    xy = np.zeros((21, 2))
    xy[0] = (100, 200)
    for f, k in enumerate((1, 5, 9, 13, 17)):
        xy[k] = (140, 185 + 7.5 * f)
        xy[k + 1] = (155, 185 + 7.5 * f)
    xy[3] = xy[2]  # the thumb's third joint (an ROI point) on its second
    c, side, a = landmarks_roi(xy)
    assert a == pytest.approx(np.pi / 2)  # wrist -> middle finger base points up in the crop
    # the box of the ROI points in the hand's frame: 55 px along the hand, 30 across; moved 0.1 x 55 towards
    # the fingers (image +x), the long side x 2
    np.testing.assert_allclose(c, [127.5 + 5.5, 200.0], atol=1e-9)
    assert side == pytest.approx(110.0)
    M = square_transform(c, side, 224, a)
    assert to_crop(M, xy[9])[1] < to_crop(M, xy[0])[1]


def test_hands_tracked_on_consecutive_frames(demo_frames, monkeypatch):
    from roomcap.keypoints import hand_model
    from roomcap.keypoints.pipeline import KeypointPipeline
    from roomcap.keypoints.runtime import RuntimeConfig

    d = need_shared("data", "pose2sim", "demo-wheel-0.10.49", "Demo_SinglePerson", "videos")
    nxt = []
    for c in ("cam01", "cam02", "cam03", "cam04"):
        cap = cv2.VideoCapture(str(d / f"{c}.mp4"))
        cap.set(cv2.CAP_PROP_POS_FRAMES, 31)
        nxt.append(cap.read()[1])
    # every frame's wrists tried (no back-off): the palm detector's turns alone (palm_every)
    pipe = KeypointPipeline(preset_config("hands", hand_retry_every=1, runtime=RuntimeConfig(threads=1)))
    first = pipe(demo_frames, streams=[0, 1, 2, 3])
    n_first = sum(int((r.score[:, -42] > 0).sum() + (r.score[:, -21] > 0).sum()) for r in first)
    assert n_first and sum(len(v) for v in pipe.hands._prev.values()) == n_first
    rois = []
    monkeypatch.setattr(hand_model, "landmarks_roi", lambda xy: rois.append(xy) or landmarks_roi(xy))
    palm_regions = pipe.hands.n_palm_regions
    second = pipe(nxt, streams=[0, 1, 2, 3])
    assert len(rois) >= n_first - 1  # the previous frame's hands placed this frame's crops
    assert pipe.hands.n_palm_regions == palm_regions  # palm_every = 8: not again on the next frame
    n_second = sum(int((r.score[:, -42] > 0).sum() + (r.score[:, -21] > 0).sum()) for r in second)
    assert n_second >= n_first - 2


def test_backoff_schedule():
    assert [backoff(m, 8) for m in range(7)] == [1, 1, 2, 4, 8, 8, 8]
    assert [backoff(m, 1) for m in range(4)] == [1, 1, 1, 1]  # 1: every turn
    assert backoff(3, 3) == 3


class _StandIn:
    """A stand-in for keypoints.runtime.OnnxModel: the real description, outputs made up. The hand landmark
    model sees a hand (landmarks spread around the crop's centre, presence ``present``) or none; the palm
    detector never finds a palm. ``runs`` counts the items run."""

    present = 0.0

    def __init__(self, spec, runtime=None):
        self.spec = registry.get_spec(spec)
        self.runs = 0

    def run(self, x):
        self.runs += len(x)
        if self.spec.role == "palm":
            return [np.zeros((len(x), 2016, 18), np.float32), np.full((len(x), 2016, 1), -50.0, np.float32)]
        lm = np.zeros((21, 3), np.float32)
        lm[:, 0] = 112 + 40 * np.cos(np.linspace(0, 5, 21))
        lm[:, 1] = 112 - np.linspace(0, 80, 21)  # the wrist (0) at the centre, the fingers up
        return [np.tile(lm.reshape(1, 63), (len(x), 1)), np.full((len(x), 1), self.present, np.float32)]


def _one_person() -> FrameResult:  # noqa: F821
    from roomcap.keypoints.pipeline_config import FrameResult

    sk = get_skeleton("body19")
    xy = np.full((1, sk.n_joints, 2), np.nan, np.float32)
    sc = np.zeros((1, sk.n_joints), np.float32)
    for name, p in {
        "left_shoulder": (260, 100),
        "left_elbow": (320, 180),
        "left_wrist": (380, 260),
        "right_shoulder": (180, 100),
        "right_elbow": (120, 180),
        "right_wrist": (60, 260),
    }.items():
        xy[0, sk.index(name)], sc[0, sk.index(name)] = p, 0.9
    return FrameResult(np.array([[150, 60, 300, 460, 0.9]], np.float32), xy, sc)


def _hand_runs(monkeypatch, retry_every: int, found_from: int = 99, frames: int = 16):
    """Per frame of one camera: the hand crops and the palm regions run, and the hands found."""
    from roomcap.keypoints import hand_model
    from roomcap.keypoints.pipeline_config import KeypointPipelineConfig
    from roomcap.keypoints.runtime import RuntimeConfig

    monkeypatch.setattr(hand_model, "OnnxModel", _StandIn)
    monkeypatch.setattr(_StandIn, "present", 0.0)
    cfg = KeypointPipelineConfig(
        hands="hand_landmark_lite", palm="palm_detection_full", palm_every=2, hand_retry_every=retry_every
    )
    stage = hand_model.HandStage(
        cfg, registry.get_spec(cfg.hands), registry.get_spec(cfg.palm), RuntimeConfig()
    )
    image = np.zeros((480, 640, 3), np.uint8)
    crops, palms, found = [], [], []
    for f in range(frames):
        if f == found_from:
            monkeypatch.setattr(_StandIn, "present", 0.9)
        c, p = stage.hand.runs, stage.palm.runs
        out = stage([image], [_one_person()], "body19", streams=["cam"])[0]
        crops.append(stage.hand.runs - c)
        palms.append(stage.palm.runs - p)
        found.append(int(out.score[0, -42] > 0) + int(out.score[0, -21] > 0))
    return crops, palms, found


def test_wrists_without_a_hand_back_off(monkeypatch):
    # no back-off: both wrists cropped on every frame, the palm detector on both every palm_every = 2 frames
    crops, palms, _ = _hand_runs(monkeypatch, 1)
    assert crops == [2] * 16
    assert palms == [2, 0] * 8
    # back-off (at most every 8): the crops after 1, 2, 4, 8 frames; the palm detector once two crops in a row
    # missed (frame 1), then after 1, 2, 4 of its turns (every 2 frames)
    crops, palms, _ = _hand_runs(monkeypatch, 8)
    assert [f for f, n in enumerate(crops) if n] == [0, 1, 3, 7, 15] and set(crops) == {0, 2}
    assert [f for f, n in enumerate(palms) if n] == [1, 3, 7, 15] and set(palms) == {0, 2}


def test_a_hand_found_again_is_tracked_on_every_frame(monkeypatch):
    # the hands appear at frame 5, while the wrists wait: found at the next try (frame 7), then tracked, a
    # crop per hand on every frame
    crops, _, found = _hand_runs(monkeypatch, 8, found_from=5)
    assert found[:7] == [0] * 7 and found[7:] == [2] * 9
    assert crops[7:] == [2] * 9
    assert sum(crops) < 2 * 16
