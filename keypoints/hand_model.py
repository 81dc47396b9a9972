"""Hand keypoints per view: MediaPipe's hand landmark model on crops placed by the body's wrist and elbow, and
its palm detector where the body does not place the hand.

For each person and side of a 2D body result (``KeypointPipelineConfig.hands`` names the landmark model):

- **forearm crop** (:func:`forearm_crop`): with the wrist and the elbow seen, a square crop centred
  ``hand_extend`` x the forearm beyond the wrist, along elbow -> wrist, of side ``hand_scale`` x the forearm's
  length (at least a share of the upper arm and of the person's box: a forearm pointing at the camera is
  short in the image), rotated so that elbow -> wrist points up: the fingers point up in it, as in the crops
  MediaPipe cuts from its palm detections (``hand_landmark_cpu.pbtxt``: a 224 x 224 crop of the hand ROI,
  rotated to the hand's direction);
- the landmark model's 21 points (MediaPipe's order, ``skeletons.hand_joints``) are mapped back to image
  pixels through the crop's inverse (``crops.apply_inverse``); its hand presence score is every joint's
  confidence; a presence under ``hand_presence`` is no hand;
- **palm detector** (``KeypointPipelineConfig.palm``): where the wrist (or the elbow, for the direction) is
  missing in the view, or the forearm crop's presence is low, an upright square region around where the hand
  is expected (``palm_region`` x the arm's reference length, centred beyond the wrist, or on the elbow when
  the wrist is missing) goes through the palm detector (:func:`decode_palms`: MediaPipe's SSD anchors,
  :func:`palm_anchors`); the best palm gives the hand crop as MediaPipe's palm -> hand ROI
  (:func:`palm_hand_roi`), and that crop's landmarks replace the forearm crop's when more present. On
  consecutive frames of a camera it runs there at most every ``palm_every`` frames (the presets: 8, as the
  body detector; it costs about 4 hand crops);
- **tracking** (consecutive frames of a camera, ``streams``): a hand found in the previous frame places the
  crop of the same side's hand near it from its landmarks (:func:`landmarks_roi`, MediaPipe's
  landmarks -> ROI), the forearm crop being the fallback where that crop loses the hand;
- **back-off** (consecutive frames of a camera, ``hand_retry_every``): a wrist whose hand its last crops did
  not find (the hand hidden, blurred, out of the frame, or a skeleton model's) is cropped again after 1, 2, 4,
  ... frames, at most ``hand_retry_every``, and the palm detector looks there after 1, 2, 4, ... of its turns
  (:func:`backoff`, :class:`Miss`): MediaPipe runs the landmark model only on the hands it tracks or its palm
  detector found, whereas the body places a crop on every wrist of every frame.

Left and right come from the body's side of the wrist used, never from the model's handedness guess (which a
mirrored view flips); the same hand found from both wrists is kept once, on the side of the nearer wrist
(``hands.hands_by_body_side``). The detections then carry the ``<layout>_hands`` skeleton, which the 3D stages
read with ``[triangulate.options] skeleton = "whole_body"``.
"""

from __future__ import annotations

import time
from collections.abc import MutableMapping
from typing import NamedTuple

import cv2
import numpy as np

from roomcap.keypoints.crops import apply_inverse, crop_transform, to_tensor
from roomcap.keypoints.hands import hands_by_body_side
from roomcap.keypoints.pipeline_config import FrameResult, KeypointPipelineConfig
from roomcap.keypoints.registry import ModelSpec
from roomcap.keypoints.runtime import OnnxModel, RuntimeConfig
from roomcap.keypoints.skeletons import get_skeleton

SIDES = ("left", "right")
N_HAND = 21
# the arm joints a body layout needs for hands (shoulders optional: they size the crop of a short forearm)
ARM = {s: (f"{s}_shoulder", f"{s}_elbow", f"{s}_wrist") for s in SIDES}


# ----------------------------------------------------------------------------- crop geometry


def arm_length(
    shoulder, elbow, wrist, person_h: float, min_upper: float = 0.8, min_frac: float = 0.12
) -> float:
    """The arm's reference length in image px: the forearm's, at least ``min_upper`` x the upper arm's and
    ``min_frac`` x the person's box height (a forearm pointing at the camera is short in the image). NaN
    points count as unknown."""
    cands = [min_frac * person_h]
    if np.isfinite(elbow).all() and np.isfinite(wrist).all():
        cands.append(float(np.linalg.norm(wrist - elbow)))
    if np.isfinite(shoulder).all() and np.isfinite(elbow).all():
        cands.append(min_upper * float(np.linalg.norm(elbow - shoulder)))
    return float(max(cands))


def up_angle(v: np.ndarray) -> float:
    """The angle (clockwise from the image's up direction) that turns direction ``v`` (image px, y down) to
    point up in a crop (``crops.crop_transform``'s convention)."""
    return float(np.arctan2(v[0], -v[1]))


def square_transform(centre, side: float, size: int, angle: float = 0.0) -> np.ndarray:
    """(2,3) affine image px -> crop px of a ``size`` x ``size`` crop of a square of ``side`` image px centred
    on ``centre``, turned by ``angle`` (clockwise; the square's up axis is the direction of that angle)."""
    c = np.asarray(centre, np.float64)
    h = 0.5 * side
    return crop_transform(np.array([c[0] - h, c[1] - h, c[0] + h, c[1] + h]), (size, size), 1.0, angle)


def forearm_crop(
    elbow: np.ndarray, wrist: np.ndarray, length: float, size: int, extend: float, scale: float
) -> np.ndarray:
    """The hand crop of a forearm: centred ``extend`` x the forearm beyond the wrist along elbow -> wrist, of
    side ``scale`` x ``length`` (``arm_length``), turned so that elbow -> wrist points up (the fingers up)."""
    d = np.asarray(wrist, np.float64) - np.asarray(elbow, np.float64)
    return square_transform(wrist + extend * d, scale * length, size, up_angle(d))


# ----------------------------------------------------------------------------- model outputs


def decode_hand_landmarks(landmarks: np.ndarray, presence: np.ndarray, corner: bool = True):
    """landmarks (B,63) = 21 x (x, y, z) crop px, presence (B,1) -> xy (B,21,2) in cv2's pixel-centre crop
    coordinates (``corner``: the model's continuous coordinates, shifted by -0.5 px), presence (B,)."""
    lm = np.asarray(landmarks, np.float32)
    if lm.ndim != 2 or lm.shape[1] != 3 * N_HAND:
        raise ValueError(f"decode_hand_landmarks: expected (B,{3 * N_HAND}), got {lm.shape}")
    xy = lm.reshape(len(lm), N_HAND, 3)[..., :2] - (0.5 if corner else 0.0)
    return xy, np.asarray(presence, np.float32).reshape(len(lm), -1)[:, 0]


def palm_anchors(size: int = 192, strides=(8, 16, 16, 16), per_layer: int = 2) -> np.ndarray:
    """Anchor centres (N,2) in input px, in the order of the palm detector's outputs: MediaPipe's
    ``SsdAnchorsCalculator`` (palm_detection_cpu.pbtxt: strides 8, 16, 16, 16, offset 0.5, aspect ratio 1 plus
    the interpolated scale = 2 anchors per layer, fixed anchor size). Consecutive layers of one stride share
    their cells: per cell (rows, then columns) that group's anchors, all at the cell's centre."""
    out = []
    i = 0
    while i < len(strides):
        j = i
        while j < len(strides) and strides[j] == strides[i]:
            j += 1
        n = -(-size // strides[i])  # feature map side, ceil
        ys, xs = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
        centres = np.stack([(xs.ravel() + 0.5) / n, (ys.ravel() + 0.5) / n], 1) * size
        out.append(np.repeat(centres, per_layer * (j - i), axis=0))
        i = j
    return np.concatenate(out)


def _nms(boxes: np.ndarray, scores: np.ndarray, iou: float) -> list[int]:
    """Greedy non-maximum suppression of boxes (N,4) x0,y0,x1,y1 (MediaPipe blends the overlapping boxes
    instead; the best one is kept here)."""
    order = list(np.argsort(-scores))
    keep: list[int] = []
    area = np.prod(np.clip(boxes[:, 2:] - boxes[:, :2], 0, None), 1)
    while order:
        k = order.pop(0)
        keep.append(int(k))
        if not order:
            break
        rest = np.array(order)
        lo = np.maximum(boxes[k, :2], boxes[rest, :2])
        hi = np.minimum(boxes[k, 2:], boxes[rest, 2:])
        inter = np.prod(np.clip(hi - lo, 0, None), 1)
        ov = inter / np.maximum(area[k] + area[rest] - inter, 1e-9)
        order = [int(r) for r, o in zip(rest, ov, strict=True) if o <= iou]
    return keep


def decode_palms(raw: np.ndarray, logits: np.ndarray, anchors: np.ndarray, score_thr: float, nms_iou: float):
    """One image's palm detector outputs, raw (N,18), logits (N,1) -> palms best first: list of (score,
    box (4,) cx, cy, w, h, keypoints (7,2)), in input px.

    MediaPipe's ``TensorsToDetectionsCalculator`` for this model (x/y/w/h scale = the input size, fixed-size
    anchors of side 1 = the input): the box centre and the keypoints are offsets in input px from the anchor's
    centre, w and h input px; the score is the sigmoid of the logit (clipped to +-100 as there)."""
    raw = np.asarray(raw, np.float64).reshape(len(anchors), -1)
    score = 1.0 / (1.0 + np.exp(-np.clip(np.asarray(logits, np.float64).reshape(-1), -100, 100)))
    idx = np.flatnonzero(score >= score_thr)
    if not len(idx):
        return []
    a = anchors[idx]
    box = raw[idx, :4].copy()
    box[:, :2] += a
    kp = raw[idx, 4:].reshape(len(idx), -1, 2) + a[:, None, :]
    xyxy = np.concatenate([box[:, :2] - box[:, 2:] / 2, box[:, :2] + box[:, 2:] / 2], 1)
    return [(float(score[idx[k]]), box[k], kp[k]) for k in _nms(xyxy, score[idx], nms_iou)]


def palm_hand_roi(box: np.ndarray, kp: np.ndarray, scale: float = 2.6, shift: float = 0.5):
    """A palm (image px: box cx, cy, w, h and its 7 keypoints) -> the hand crop's centre, side and angle, as
    MediaPipe's palm -> hand ROI (palm_detection_detection_to_roi.pbtxt: rotation from keypoint 0, the wrist,
    to keypoint 2, the middle finger's base, pointing up; the rect moved by ``shift`` x its height towards the
    fingers, its long side x ``scale``)."""
    angle = up_angle(kp[2] - kp[0])
    up = np.array([np.sin(angle), -np.cos(angle)])
    centre = box[:2] + shift * box[3] * up
    return centre, scale * float(max(box[2], box[3])), angle


# MediaPipe's hand landmarks -> ROI (hand_landmark_landmarks_to_roi.pbtxt): the wrist, the thumb's first two
# joints and the first two of every finger span the box
ROI_POINTS = (0, 1, 2, 3, 5, 6, 9, 10, 13, 14, 17, 18)


def landmarks_roi(xy: np.ndarray, scale: float = 2.0, shift: float = 0.1):
    """A hand's 21 landmarks (image px) -> the next frame's crop centre, side and angle, as MediaPipe tracks a
    hand (hand_landmark_landmarks_to_roi.pbtxt): turned so that the wrist -> middle finger base (landmarks 0
    -> 9) points up, the box of the ``ROI_POINTS`` in that frame moved by ``shift`` x its height towards the
    fingers, its long side x ``scale``."""
    a = up_angle(xy[9] - xy[0])
    c, n = np.cos(a), np.sin(a)
    R = np.array([[c, n], [-n, c]])  # image -> the upright hand's frame (crops.crop_transform)
    q = xy[list(ROI_POINTS)] @ R.T
    lo, hi = q.min(0), q.max(0)
    w, h = hi - lo
    centre = R.T @ (0.5 * (lo + hi)) + shift * h * np.array([n, -c])
    return centre, scale * float(max(w, h)), a


# ----------------------------------------------------------------------------- the stage


class Miss(NamedTuple):
    """A wrist of a stream's frame whose hand was not found: its side index, position (image px), the
    fruitless forearm crops in a row there and the frames since the last, the fruitless palm detector runs in
    a row and the palm detector's turns (``palm_every``) passed over since the last."""

    side: int
    wrist: np.ndarray
    tries: int = 0
    waited: int = 0
    palm_tries: int = 0
    palm_waited: int = 0


def backoff(tries: int, cap: int) -> int:
    """Exponential back-off: after ``tries`` fruitless tries in a row, the next try is this many turns after
    the last: 1, 1, 2, 4, ... at most ``cap`` (1 = every turn)."""
    return max(1, min(2 ** max(tries - 1, 0), cap))


class HandStage:
    """The hand models of one 2D pipeline: ``__call__(images, results, skeleton)`` appends both hands to each
    person of each image's body result (layout ``skeleton`` -> ``<skeleton>_hands``). ``stage_s`` (the
    pipeline's) accumulates the seconds of ``hand_crop``, ``hand`` (model runs), ``hand_post``, ``palm``."""

    def __init__(
        self,
        config: KeypointPipelineConfig,
        hand_spec: ModelSpec,
        palm_spec: ModelSpec | None,
        runtime: RuntimeConfig,
        stage_s: MutableMapping[str, float] | None = None,
    ):
        self.config = config
        self.hand = OnnxModel(hand_spec, runtime)
        self.palm = OnnxModel(palm_spec, runtime) if palm_spec is not None else None
        self.stage_s: MutableMapping[str, float] = stage_s if stage_s is not None else {}
        d = self.hand.spec.decoder
        self.presence = config.hand_presence or d.presence_threshold
        if self.palm is not None:
            pd = self.palm.spec.decoder
            self.anchors = palm_anchors(self.palm.spec.input.size_wh[0], pd.strides)
        self.n_crops = self.n_palm_regions = self.n_palm_hands = 0
        self._prev: dict = {}  # stream -> [(side index, (21,2) image px)] of its previous frame's hands
        self._palm_age: dict = {}  # stream -> frames since the palm detector last ran on it
        self._missed: dict = {}  # stream -> [Miss] of its previous frame's wrists whose hand was not found
        self.n_waiting = 0  # forearm crops not run: their wrist waits (``hand_retry_every``)

    @property
    def models(self) -> list[OnnxModel]:
        return [m for m in (self.hand, self.palm) if m is not None]

    def _tick(self, name: str, t0: float) -> float:
        t = time.perf_counter()
        self.stage_s[name] = self.stage_s.get(name, 0.0) + t - t0
        return t

    def _landmarks(self, images, owner: list[int], Ms: np.ndarray):
        """The landmark model on crops ``Ms`` (N,2,3) of images ``owner`` -> xy (N,21,2) image px and
        presence (N,)."""
        spec = self.hand.spec
        W, H = spec.input.size_wh
        t = time.perf_counter()
        if not len(Ms):
            return np.zeros((0, N_HAND, 2)), np.zeros(0)
        crops = np.empty((len(Ms), H, W, 3), np.uint8)
        for k, (i, M) in enumerate(zip(owner, Ms, strict=True)):
            cv2.warpAffine(
                images[i], M, (W, H), dst=crops[k], flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT
            )
        x = to_tensor(crops, spec)
        t = self._tick("hand_crop", t)
        outs = self.hand.run(x)
        t = self._tick("hand", t)
        xy, pres = decode_hand_landmarks(outs[0], outs[1], spec.decoder.pixel_coords == "corner")
        xy = apply_inverse(Ms, xy.astype(np.float64))
        self._tick("hand_post", t)
        self.n_crops += len(Ms)
        return xy, pres

    def _palms(self, images, owner: list[int], Ms: np.ndarray) -> list[tuple | None]:
        """The palm detector on upright regions ``Ms`` of images ``owner`` -> per region its best palm (box
        (4,) cx, cy, w, h and keypoints (7,2), image px), or None."""
        assert self.palm is not None
        spec = self.palm.spec
        W, H = spec.input.size_wh
        t = time.perf_counter()
        crops = np.empty((len(Ms), H, W, 3), np.uint8)
        for k, (i, M) in enumerate(zip(owner, Ms, strict=True)):
            cv2.warpAffine(
                images[i], M, (W, H), dst=crops[k], flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT
            )
        outs = self.palm.run(to_tensor(crops, spec))
        d = spec.decoder
        shift = 0.5 if d.pixel_coords == "corner" else 0.0
        res: list[tuple | None] = []
        for k in range(len(Ms)):
            palms = decode_palms(outs[0][k], outs[1][k], self.anchors, d.score_threshold, d.nms_iou)
            if not palms:
                res.append(None)
                continue
            _, box, kp = palms[0]
            pts = apply_inverse(Ms[k : k + 1], np.vstack([box[:2], kp])[None] - shift)[0]
            s = 1.0 / np.sqrt(abs(np.linalg.det(Ms[k][:, :2])))  # image px per input px
            res.append((np.r_[pts[0], box[2:] * s], pts[1:]))
        self.n_palm_regions += len(Ms)
        self._tick("palm", t)
        return res

    def __call__(self, images, results: list[FrameResult], skeleton: str, streams=None) -> list[FrameResult]:
        """Both hands of every person of ``results`` (layout ``skeleton``) -> results in ``<skeleton>_hands``.

        ``streams``: one key per image (the camera) for consecutive frames: a hand found in a stream's
        previous frame places this frame's crop from its landmarks (:func:`landmarks_roi`, MediaPipe's
        tracking), the forearm crop then being the fallback; and the palm detector runs on a stream at most
        every ``palm_every`` frames."""
        cfg = self.config
        sk = get_skeleton(skeleton)
        idx = {s: [sk.index(n) if n in sk.joint_names else -1 for n in ARM[s]] for s in SIDES}
        hand_size = self.hand.spec.input.size_wh[0]
        keys = list(streams) if streams is not None else [None] * len(images)
        # every (image, person, side): its arm joints, reference length, crop or palm region
        jobs = []  # (image, person, side index, shoulder, elbow, wrist, length)
        for i, r in enumerate(results):
            for p in range(len(r.xy_px)):
                h = float(r.boxes[p, 3] - r.boxes[p, 1]) if len(r.boxes) > p else 0.0
                for si, s in enumerate(SIDES):
                    pts = []
                    for j in idx[s]:
                        ok = j >= 0 and r.score[p, j] >= cfg.hand_joint_score
                        pts.append(np.asarray(r.xy_px[p, j], np.float64) if ok else np.full(2, np.nan))
                    sh, el, wr = pts
                    jobs.append((i, p, si, sh, el, wr, arm_length(sh, el, wr, h)))
        n = len(jobs)
        xy = np.full((n, N_HAND, 2), np.nan)
        pres = np.zeros(n)
        t = time.perf_counter()
        tracked = self._tracked_rois(jobs, keys, hand_size)
        forearm = {
            k: forearm_crop(j[4], j[5], j[6], hand_size, cfg.hand_extend, cfg.hand_scale)
            for k, j in enumerate(jobs)
            if np.isfinite(j[4]).all() and np.isfinite(j[5]).all()
        }
        # back-off (``Miss``, ``backoff``): a wrist whose hand its last crops did not find waits for the next
        missed = self._match_missed(jobs, keys, tracked) if streams is not None else {}
        every = cfg.hand_retry_every
        waiting = {k for k, m in missed.items() if k in forearm and m.waited + 1 < backoff(m.tries, every)}
        first = {k: tracked.get(k, forearm.get(k)) for k in range(n) if k in tracked or k in forearm}
        first = {k: M for k, M in first.items() if k not in waiting}
        self.n_waiting += len(waiting)
        self._tick("hand_crop", t)
        self._run_crops(images, jobs, first, xy, pres)
        # a tracked crop that lost the hand: the forearm's
        lost = {k: forearm[k] for k in tracked if k in forearm and pres[k] < self.presence}
        self._run_crops(images, jobs, lost, xy, pres)
        palm_due, palm_ran = [False] * len(images), set()
        if self.palm is not None:
            age = self._palm_age
            palm_due = [streams is None or age.get(key, cfg.palm_every) >= cfg.palm_every for key in keys]
            # ... and so does the palm detector, counting its turns (every ``palm_every`` frames); with the
            # back-off on, it looks beside a forearm crop only once two crops in a row missed there (a hand
            # missed on one frame is mostly found by the next crop)
            palm_waits = {k for k, m in missed.items() if m.palm_waited + 1 < backoff(m.palm_tries, every)}
            fresh = set()  # (the stream's turn stays open for them)
            if streams is not None and every > 1:
                fresh = {k for k in forearm if (missed[k].tries if k in missed else 0) + (k in first) < 2}
            palm_jobs = [
                j if palm_due[j[0]] and k not in palm_waits and k not in fresh else None
                for k, j in enumerate(jobs)
            ]
            ran, palm_ran = self._palm_fallback(images, palm_jobs, xy, pres, hand_size)
            # a wrist that waits takes its turn
            waited = {jobs[k][0] for k in palm_waits - fresh if pres[k] < self.presence}
            ran |= {i for i in waited if palm_due[i]}
            if streams is not None:
                for i, key in enumerate(keys):
                    age[key] = 1 if i in ran else age.get(key, cfg.palm_every) + 1
        out = self._attach(results, jobs, xy, pres, skeleton)
        if streams is not None:
            self._missed = {key: [] for key in keys}
            for k, (i, _, si, _, _, wr, _) in enumerate(jobs):
                if pres[k] < self.presence and np.isfinite(wr).all():
                    m = missed.get(k, Miss(si, wr))
                    tries, waited = (m.tries, m.waited + 1) if k in waiting else (m.tries + (k in first), 0)
                    p_tries, p_waited = m.palm_tries, m.palm_waited
                    if k in palm_ran:
                        p_tries, p_waited = p_tries + 1, 0
                    elif palm_due[i]:
                        p_waited += 1
                    self._missed[keys[i]].append(Miss(si, wr, tries, waited, p_tries, p_waited))
            for key, r in zip(keys, out, strict=True):
                J = r.xy_px.shape[1] - 2 * N_HAND
                self._prev[key] = [
                    (si, r.xy_px[p, J + si * N_HAND : J + (si + 1) * N_HAND].astype(np.float64))
                    for p in range(len(r.xy_px))
                    for si in range(2)
                    if r.score[p, J + si * N_HAND] > 0
                ]
        return out

    def reset_streams(self) -> None:
        """Forget the hands of every stream's previous frame, its wrists without a hand and when the palm
        detector last ran."""
        self._prev.clear()
        self._palm_age.clear()
        self._missed.clear()

    def _run_crops(self, images, jobs, crops: dict, xy, pres) -> None:
        """The landmark model on ``crops`` {job: affine}; a job takes the result where more present."""
        if not crops:
            return
        ks = list(crops)
        hxy, hp = self._landmarks(images, [jobs[k][0] for k in ks], np.array([crops[k] for k in ks]))
        for k, h, p in zip(ks, hxy, hp, strict=True):
            if p > pres[k]:
                xy[k], pres[k] = h, p

    def _match_missed(self, jobs, keys, tracked: dict) -> dict:
        """{job: Miss} of this frame's wrists (not placed by a tracked hand) near a wrist of the stream's
        previous frame whose hand was not found (``_missed``): same side, within ``track_reach`` x the arm's
        length, nearest first, each used once."""
        cands = []
        for k, (i, _, si, _, _, wr, length) in enumerate(jobs):
            if k in tracked or not np.isfinite(wr).all():
                continue
            for h, miss in enumerate(self._missed.get(keys[i], [])):
                if miss.side == si:
                    d = float(np.linalg.norm(miss.wrist - wr))
                    if d < self.config.track_reach * length:
                        cands.append((d, k, (keys[i], h), miss))
        out: dict = {}
        used = set()
        for _, k, h, miss in sorted(cands, key=lambda c: c[0]):
            if k not in out and h not in used:
                used.add(h)
                out[k] = miss
        return out

    def _tracked_rois(self, jobs, keys, hand_size) -> dict:
        """{job: affine} of the crops placed by the stream's previous-frame hands: each hand of that side
        whose root lies within ``track_reach`` x the arm's length of this person's wrist (of the elbow, at
        twice the reach, when the wrist is missing), nearest first, each previous hand used once."""
        cands = []
        for k, (i, _, si, _, el, wr, length) in enumerate(jobs):
            anchor, reach = (wr, 1.0) if np.isfinite(wr).all() else (el, 2.0)
            if not np.isfinite(anchor).all():
                continue
            for h, (psi, pxy) in enumerate(self._prev.get(keys[i], [])):
                if psi != si or not np.isfinite(pxy[0]).all():
                    continue
                d = float(np.linalg.norm(pxy[0] - anchor))
                if d < reach * self.config.track_reach * length:
                    cands.append((d, k, (keys[i], h), pxy))
        out: dict = {}
        used = set()
        for _, k, h, pxy in sorted(cands, key=lambda c: c[0]):
            if k in out or h in used:
                continue
            used.add(h)
            c, side, a = landmarks_roi(pxy)
            out[k] = square_transform(c, side, hand_size, a)
        return out

    def _palm_fallback(self, images, jobs, xy, pres, hand_size) -> tuple[set[int], set[int]]:
        """The palm detector where the forearm crop was not possible or found no hand (module doc), for the
        jobs that are not None. Returns the images it ran on and the jobs it looked for a hand for."""
        cfg = self.config
        t = time.perf_counter()
        region_k, regions = [], []
        for k, job in enumerate(jobs):
            if job is None or pres[k] >= self.presence:
                continue
            _, _, _, _, el, wr, length = job
            if np.isfinite(wr).all():
                d = wr - el if np.isfinite(el).all() else np.zeros(2)
                centre = wr + cfg.hand_extend * d
            elif np.isfinite(el).all():
                centre = el
            else:
                continue  # no arm to look along
            region_k.append(k)
            side = cfg.palm_region * length
            regions.append(square_transform(centre, side, self.palm.spec.input.size_wh[0]))
        self._tick("palm", t)
        if not region_k:
            return set(), set()
        palms = self._palms(images, [jobs[k][0] for k in region_k], np.array(regions))
        t = time.perf_counter()
        found = [(k, p) for k, p in zip(region_k, palms, strict=True) if p is not None]
        rois = [palm_hand_roi(*p) for _, p in found]  # (centre, side, angle)
        Ms = np.array([square_transform(c, side, hand_size, a) for c, side, a in rois]).reshape(-1, 2, 3)
        self._tick("palm", t)
        ran = {jobs[k][0] for k in region_k}
        if not found:
            return ran, set(region_k)
        pxy, ppres = self._landmarks(images, [jobs[k][0] for k, _ in found], Ms)
        for (k, _), h, s in zip(found, pxy, ppres, strict=True):
            if s > pres[k]:
                xy[k], pres[k] = h, s
                self.n_palm_hands += int(s >= self.presence)
        return ran, set(region_k)

    def _attach(self, results, jobs, xy, pres, skeleton) -> list[FrameResult]:
        t = time.perf_counter()
        out = []
        hands_xy = [np.full((len(r.xy_px), 2 * N_HAND, 2), np.nan, np.float32) for r in results]
        hands_sc = [np.zeros((len(r.xy_px), 2 * N_HAND), np.float32) for r in results]
        for (i, p, si, *_), h, s in zip(jobs, xy, pres, strict=True):
            if s >= self.presence:
                hands_xy[i][p, si * N_HAND : (si + 1) * N_HAND] = h
                hands_sc[i][p, si * N_HAND : (si + 1) * N_HAND] = s
        out_sk = f"{skeleton}_hands"
        for r, hx, hs in zip(results, hands_xy, hands_sc, strict=True):
            J = get_skeleton(skeleton).n_joints  # (an image without people has (0, 0, 2) arrays)
            bxy = np.concatenate([np.asarray(r.xy_px, np.float32).reshape(len(hx), J, 2), hx], 1)
            bsc = np.concatenate([np.asarray(r.score, np.float32).reshape(len(hx), J), hs], 1)
            if len(bxy):  # one hand found from both wrists: kept once, on the nearer wrist's side
                bxy, bsc, _ = hands_by_body_side(bxy, bsc, out_sk)
                bxy[bsc <= 0] = np.nan
            bxy, bsc = bxy.astype(np.float32), bsc.astype(np.float32)
            out.append(FrameResult(r.boxes, bxy, bsc, r.maps, r.maps_to_img))
        self._tick("hand_post", t)
        return out
