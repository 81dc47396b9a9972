"""Per-image multi-person 2D keypoints: top-down (detector -> crops -> pose model) and bottom-up.

``KeypointPipeline(model_set)`` takes a list of BGR images (one per camera, any sizes) and returns one
``FrameResult`` per image with boxes, keypoints in full-image pixels and scores, in the canonical
``body19`` layout (``keypoints.skeletons.convert``; the 3D stages read body19). Images are processed
as one batch: one detector run over all cameras, one pose run over every person crop of every camera
(where the model's batch dimension is dynamic; see ``keypoints.runtime``).

Top-down crops are square (or the model's aspect) around the detector box times ``box_padding``, cut
by one affine warp, so portrait 1080x1920 frames and people near the border are handled the same way
(outside the image is filled with the pad value). The detectors give no orientation: the first pass is
upright, people it finds weakly are tried again in crops turned by 90/180/270 degrees (rotation
hypotheses), and the refine passes turn each crop so that the body (hips -> shoulders) stands upright.
Where two poses of one image coincide (an occluded person's crop returning the person in front), each is
estimated again with the other person erased and the better reading kept, or one of them is dropped.
``stage_s`` accumulates seconds per stage for the benchmark.

The settings and the per-image result are in :mod:`roomcap.keypoints.pipeline_config`, the crop geometry in
:mod:`roomcap.keypoints.crops`, the pose hypotheses (flip, rotation, duplicates) in
:mod:`roomcap.keypoints.hypotheses`.
"""

from __future__ import annotations

import logging
import time
from collections import defaultdict
from dataclasses import dataclass

import cv2
import numpy as np

from roomcap.keypoints import decoders as D
from roomcap.keypoints.crops import (
    apply_inverse,
    containing_region,
    crop_region,
    crop_transform,
    keypoint_boxes,
    letterbox,
    level_offset,
    to_tensor,
    upright_boxes,
)
from roomcap.keypoints.hand_model import HandStage
from roomcap.keypoints.hypotheses import (
    _duplicate_pairs,
    _erase_body,
    _keypoint_box_iou,
    _strong_or_apart,
    consensus,
    hide_face_from_behind,
    merge_hypotheses,
)
from roomcap.keypoints.pipeline_config import FrameResult, KeypointPipelineConfig
from roomcap.keypoints.registry import BODY_ROLES, ModelSpec, get_model_set, get_spec
from roomcap.keypoints.runtime import OnnxModel
from roomcap.keypoints.skeletons import convert, get_skeleton

log = logging.getLogger(__name__)


@dataclass
class _Seed:
    """A stream's people in its last frame: poses (M,J,2), scores (M,J) in the model's skeleton, their
    keypoint boxes (M,5); frames since the detector ran; whether someone was lost in that frame."""

    xy: np.ndarray
    sc: np.ndarray
    boxes: np.ndarray
    age: int = 0
    lost: bool = False


# ----------------------------------------------------------------------------- the pipeline


class KeypointPipeline:
    def __init__(self, config: KeypointPipelineConfig | str = "default"):
        if isinstance(config, str):
            config = KeypointPipelineConfig(model_set=config)
        self.config = config
        self.model_set = get_model_set(config.model_set)
        md = config.runtime.model_dir or None
        self.pose_spec = get_spec(self.model_set.pose, md)
        self.det_spec = get_spec(self.model_set.detector, md) if self.model_set.detector else None
        if self.pose_spec.role == "pose" and self.det_spec is None:
            raise ValueError(
                f"model set '{config.model_set}': pose model '{self.pose_spec.name}' is top-down and "
                "needs a detector ('detector+pose')."
            )
        if self.det_spec is not None and self.det_spec.role != "detector":
            raise ValueError(f"model '{self.det_spec.name}' is a {self.det_spec.role}, not a detector.")
        if self.pose_spec.role not in BODY_ROLES:
            spec = self.pose_spec
            raise ValueError(f"model '{spec.name}' is a {spec.role} model, not a body model.")
        hand_spec, palm_spec = self._hand_specs(md)
        self.pose = OnnxModel(self.pose_spec, config.runtime)
        self.detector = OnnxModel(self.det_spec, config.runtime) if self.det_spec else None
        self.src_skeleton = self.pose_spec.skeleton
        # the body's layout (the hands, when on, are appended to it: ``<layout>_hands``)
        self.body_skeleton = self.src_skeleton if config.skeleton == "model" else config.skeleton
        if hand_spec is not None and self.body_skeleton.endswith("_hands"):
            self.body_skeleton = self.body_skeleton[: -len("_hands")]
        self.skeleton = self.body_skeleton + ("_hands" if hand_spec is not None else "")
        get_skeleton(self.skeleton)
        self.stage_s: dict[str, float] = defaultdict(float)
        self.hands = None if hand_spec is None else HandStage(config, hand_spec, palm_spec, config.runtime)
        if self.hands is not None:
            self.hands.stage_s = self.stage_s
        self.call_cpu_s = 0.0  # CPU time of the calling thread in __call__ (the models': model_run_cpu_s)
        # pyramid regions per (image, level) for the current call: (x0, y0, x1, y1, level image)
        self._pyr: dict[tuple[int, int], list[tuple[int, int, int, int, np.ndarray]]] = {}
        self._seeds: dict = {}  # stream -> _Seed (tracked crops)
        self.n_detected = self.n_tracked = (
            0  # images that ran the detector / were cropped from the last poses
        )

    def _hand_specs(self, model_dir):
        """The hand landmark and palm detector descriptions ``config.hands`` and ``config.palm`` (None: off);
        their files are resolved when the models open (a missing one is named with the folders searched)."""
        cfg = self.config
        if not cfg.hands:
            if cfg.palm:
                raise ValueError("KeypointPipelineConfig.palm needs hands (the hand landmark model) on.")
            return None, None
        hand = get_spec(cfg.hands, model_dir)
        palm = get_spec(cfg.palm, model_dir) if cfg.palm else None
        for spec, role in ((hand, "hand"), (palm, "palm")):
            if spec is not None and spec.role != role:
                raise ValueError(f"model '{spec.name}' is a {spec.role} model, not a {role} model.")
        return hand, palm

    # identity of what produced the keypoints (goes into the detections file)
    @property
    def model_id(self) -> str:
        return "+".join(m.spec.name for m in self.models)

    @property
    def model_sha256(self) -> str:
        return "+".join(m.sha256 for m in self.models)

    @property
    def models(self) -> list[OnnxModel]:
        body = [m for m in (self.detector, self.pose) if m is not None]
        return body + (self.hands.models if self.hands is not None else [])

    def model_run_s(self) -> float:
        return sum(m.run_s for m in self.models)

    def model_run_cpu_s(self) -> float:
        return sum(m.run_cpu_s for m in self.models)

    def _tick(self, name: str, t0: float) -> float:
        t = time.perf_counter()
        self.stage_s[name] += t - t0
        return t

    def __call__(self, images: list[np.ndarray], streams=None) -> list[FrameResult]:
        """images: list of (H,W,3) uint8 BGR (sizes may differ). Returns one FrameResult per image.

        ``streams``: one key per image (the camera), for consecutive frames of videos: with
        ``config.detect_every`` > 1 the previous frame's poses of that stream place the crops (``_tracked``).
        None: every image on its own (the detector on each)."""
        for i, im in enumerate(images):
            if im.ndim != 3 or im.shape[2] != 3 or im.dtype != np.uint8:
                raise ValueError(f"image {i}: expected (H,W,3) uint8 BGR, got {im.shape} {im.dtype}")
        if not images:
            return []
        c = time.thread_time()
        try:
            return self._call(images, streams)
        finally:
            self.call_cpu_s += time.thread_time() - c

    def _call(self, images, streams):
        role = self.pose_spec.role
        if role == "pose":
            res = self._top_down(images, streams)
        elif role == "onestage":
            res = self._one_stage(images)
        else:
            res = self._bottom_up(images)
        if self.hands is not None:  # both hands of every person, from its wrists (keypoints.hand_model)
            res = self.hands(images, res, self.body_skeleton, streams)
        return res

    # ---- whole-image models: letterbox all images into one batch
    def _letterbox_batch(self, images, spec: ModelSpec):
        W, H = spec.input.size_wh
        canv = np.empty((len(images), H, W, 3), np.uint8)
        ratios = np.empty(len(images))
        for i, im in enumerate(images):
            _, ratios[i] = letterbox(im, (W, H), spec.input.pad_value, out=canv[i])
        return to_tensor(canv, spec), ratios

    def detect(self, images: list[np.ndarray]) -> list[np.ndarray]:
        """Person boxes per image (M,5) in image px, best first, at most max_people."""
        spec = self.det_spec
        t = time.perf_counter()
        x, ratios = self._letterbox_batch(images, spec)
        t = self._tick("detect_pre", t)
        outs = self.detector.run(x)
        t = self._tick("detect", t)
        d = spec.decoder
        thr = self.config.det_score or d.score_threshold
        weak = self.config.det_score_weak
        lo = weak if 0 < weak < thr else thr
        if d.kind == "yolox":
            boxes = D.decode_yolox(outs[0], spec.input.size_wh, d.strides, d.class_id, lo, d.nms_iou)
        else:
            boxes = D.decode_dets(outs[0], outs[1] if len(outs) > 1 else None, d.class_id, lo, d.nms_iou)
        res = []
        for b, r, im in zip(boxes, ratios, images, strict=True):
            b = b[_strong_or_apart(b, thr)] if lo < thr else b.copy()
            b[:, :4] /= r
            h, w = im.shape[:2]
            b[:, [0, 2]] = b[:, [0, 2]].clip(0, w)
            b[:, [1, 3]] = b[:, [1, 3]].clip(0, h)
            b = b[(b[:, 3] - b[:, 1]) >= self.config.min_box_px]
            res.append(b[np.argsort(-b[:, 4])][: self.config.max_people])
        self._tick("detect_post", t)
        return res

    def pose_on_boxes(
        self,
        images: list[np.ndarray],
        boxes: list[np.ndarray],
        angles: list[np.ndarray] | None = None,
        scales: tuple[float, ...] = (1.0,),
        flip: bool | None = None,
    ):
        """Run the pose model on every box of every image as one batch.

        Returns per image (xy (M,J,2) image px, score (M,J), person (M,), roi) in the model's skeleton;
        ``roi`` (M,5) = box x0,y0,x1,y1 + tilt angle for the next pass where the model gives one (BlazePose's
        alignment points, as mediapipe's landmarks-to-ROI tracking step), else None. ``scales``: crop sizes
        (x the padding) whose results are averaged (test-time augmentation, one batch).
        """
        spec = self.pose_spec
        W, H = spec.input.size_wh
        pad = self.config.box_padding or spec.input.box_padding
        t = time.perf_counter()
        scales = tuple(scales) or (1.0,)
        n0 = sum(len(b) for b in boxes)
        n = n0 * len(scales)  # crops ordered scale-major: crop s * n0 + person
        crops = np.empty((n, H, W, 3), np.uint8)
        Ms = np.empty((n, 2, 3))
        owner = np.empty(n, int)
        k = 0
        for i, bs, f in ((i, bs, f) for f in scales for i, bs in enumerate(boxes)):
            for j, b in enumerate(bs):
                Ms[k] = crop_transform(b, (W, H), pad * f, 0.0 if angles is None else angles[i][j])
                owner[k] = i
                k += 1
        levels = self._person_levels(Ms, len(scales))
        for k, (src, M) in enumerate(self._crop_sources(images, owner, Ms, (W, H), levels)):
            cv2.warpAffine(
                src,
                M,
                (W, H),
                dst=crops[k],
                flags=cv2.INTER_LINEAR,
                borderMode=cv2.BORDER_CONSTANT,
                borderValue=(spec.input.pad_value,) * 3,
            )
        if flip is None:
            flip = spec.decoder.flip_test if self.config.flip_test is None else self.config.flip_test
        flip = n > 0 and flip
        if flip:  # test-time augmentation: the mirrored crops go in the same batch
            crops = np.concatenate([crops, crops[:, :, ::-1]])
        x = to_tensor(crops, spec) if n else None
        t = self._tick("crop", t)
        outs = self.pose.run(x) if n else None
        t = self._tick("pose", t)
        xy, sc, person, roi = self._decode_pose(outs, n * (2 if flip else 1), (W, H))
        if flip:
            fi = get_skeleton(spec.skeleton).flip_index
            xf = xy[n:, fi].copy()
            xf[..., 0] = (W - 1) - xf[..., 0]  # pixel-centre coordinates: column i -> W - 1 - i
            xy, sc = merge_hypotheses(xy[:n], sc[:n], xf, sc[n:, fi], self.config.flip_agree * W)
            person = 0.5 * (person[:n] + person[n:])
            roi = None if roi is None else roi[:n]
        if n:
            xy = apply_inverse(Ms, xy)
            if roi is not None:
                roi = self._roi_to_image(roi[:n0], Ms[:n0])
        if len(scales) > 1 and n0:  # multi-scale test-time augmentation: consensus over the crops
            S = len(scales)
            xy, sc, person = xy.reshape(S, n0, -1, 2), sc.reshape(S, n0, -1), person.reshape(S, n0)
            side = W / np.sqrt(np.abs(np.linalg.det(Ms[:n0, :, :2])))  # crop side in image px (M,)
            xy, sc = consensus(xy, sc, self.config.flip_agree * side[:, None])
            person = person.mean(0)
        res, k = [], 0
        for bs in boxes:
            m = len(bs)
            res.append(
                (xy[k : k + m], sc[k : k + m], person[k : k + m], None if roi is None else roi[k : k + m])
            )
            k += m
        self._tick("pose_post", t)
        return res

    def _level(self, M: np.ndarray) -> int:
        """The pyramid level a crop of affine M is cut from: a crop that shrinks the image more than 2x comes
        from a Gaussian pyramid level (cv2.pyrDown), avoiding the aliasing of warpAffine's bilinear
        sampling; 0 = the image itself."""
        if not self.config.antialias:
            return 0
        scale = float(np.sqrt(abs(np.linalg.det(M[:, :2]))))
        return int(np.clip(np.floor(np.log2(1.0 / max(scale, 1e-9))), 0, 4))

    def _person_levels(self, Ms: np.ndarray, n_scales: int) -> np.ndarray:
        """The pyramid level of each crop of ``Ms`` (ordered scale-major: crop s * n + person): one level
        per person for all its crop sizes, its largest crop's. Sizes on either side of a level's bound would
        otherwise reduce the same pixels to two levels."""
        n = len(Ms) // max(n_scales, 1)
        per = np.array([self._level(M) for M in Ms], int).reshape(n_scales, n).max(0, initial=0)
        return np.tile(per, n_scales)

    def _reduce(self, image: np.ndarray, last: bool) -> np.ndarray:
        """One pyramid level down: cv2.pyrDown, or the means of 2x2 pixels (an odd last row or column is
        dropped) for ``pyramid = "box"`` and for the levels of ``"mixed"`` before the ``last``."""
        if self.config.pyramid == "gaussian" or (self.config.pyramid == "mixed" and last):
            return cv2.pyrDown(image)
        h, w = max(image.shape[0] // 2, 1), max(image.shape[1] // 2, 1)
        return cv2.resize(image[: 2 * h, : 2 * w], (w, h), interpolation=cv2.INTER_AREA)

    def _crop_sources(self, images, owner: np.ndarray, Ms: np.ndarray, size_wh: tuple[int, int], levels=None):
        """Per crop (of image ``owner[k]``, affine ``Ms[k]``), the image level to cut it from (``levels[k]``,
        default ``_level``) and the affine for that level.

        pyrDown centres its kernel on source pixel 2i, so level-L pixels relate to image pixels by
        x = 2^L x_L. Only the region a crop samples is reduced (``crop_region``: with the kernels' reach as
        margin and its corner on the level-L grid, so the pixels equal those of the whole image's pyramid);
        per image and level, overlapping regions are merged into one (people close together, the crop
        sizes of the test-time augmentation) so that each pixel is reduced once, and the regions are kept
        for this call's passes (``self._pyr``).
        """
        levels = [self._level(M) for M in Ms] if levels is None else [int(L) for L in levels]
        need = [
            crop_region(M, size_wh, images[i].shape, 2**L) if L else None
            for i, M, L in zip(owner, Ms, levels, strict=True)
        ]
        want: dict[tuple[int, int], list] = {}
        for i, L, box in zip(owner, levels, need, strict=True):
            if L:
                want.setdefault((int(i), L), []).append(box)
        for (i, L), boxes in want.items():
            have = self._pyr.setdefault((i, L), [])
            merged: list[list[int]] = []
            for box in sorted(b for b in boxes if containing_region(have, b) is None):
                for m in merged:
                    if box[0] < m[2] and m[0] < box[2] and box[1] < m[3] and m[1] < box[3]:
                        m[:] = [min(m[0], box[0]), min(m[1], box[1]), max(m[2], box[2]), max(m[3], box[3])]
                        break
                else:
                    merged.append(list(box))
            for x0, y0, x1, y1 in merged:
                level = images[i][y0:y1, x0:x1]
                for k in range(L):
                    level = self._reduce(level, last=k == L - 1)
                have.append((x0, y0, x1, y1, level))
        out = []
        for i, M, L, box in zip(owner, Ms, levels, need, strict=True):
            if not L:
                out.append((images[i], M))
                continue
            x0, y0, _, _, level = containing_region(self._pyr[(int(i), L)], box)
            # crop px = A x + t with x = (region x0, y0) + 2^L x_L + c (level_offset)
            c = level_offset(L, self.config.pyramid)
            A = M[:, :2]
            out.append((level, np.hstack([A * 2**L, (M[:, 2] + A @ np.array([x0 + c, y0 + c]))[:, None]])))
        return out

    @staticmethod
    def _roi_to_image(aux: np.ndarray, Ms: np.ndarray) -> np.ndarray:
        """BlazePose alignment points (N,2,2) crop px -> ROI (N,5) for the next pass: centre at the hips,
        square of side 2 x the full-body radius (then x box_padding = 1.25 as mediapipe), rotated so that
        hips -> head points up."""
        a = apply_inverse(Ms, aux)
        v = a[:, 1] - a[:, 0]
        r = np.linalg.norm(v, axis=1, keepdims=True)
        return np.concatenate([a[:, 0] - r, a[:, 0] + r, np.arctan2(v[:, :1], -v[:, 1:2])], 1)

    def _decode_pose(self, outs, n: int, size_wh):
        """Pose outputs -> xy (n,J,2) crop px, score (n,J), person (n,), BlazePose ROI points or None."""
        spec = self.pose_spec
        d = spec.decoder
        J = get_skeleton(spec.skeleton).n_joints
        roi = None
        if n == 0:
            xy, sc, person = np.zeros((0, J, 2)), np.zeros((0, J)), np.zeros(0)
        elif d.kind == "blazepose":
            xy, sc, person, aux = D.decode_blazepose(outs[0], outs[1], d.n_landmarks)
            if aux.shape[1] >= 2:
                roi = aux[:, :2]
        elif d.kind == "movenet":
            xy, sc = D.decode_movenet(outs[0], size_wh)
            person = sc.mean(1)
        elif d.kind == "simcc":
            xy, sc = D.decode_simcc(outs[0], outs[1], d.split_ratio)
            person = sc.mean(1)
        else:  # pragma: no cover - registry validates role/decoder pairs
            raise ValueError(f"decoder {d.kind} is not a top-down pose decoder")
        if d.pixel_coords == "corner":  # to cv2.warpAffine's pixel-centre coordinates: x_c = x - 0.5
            # Demo_SinglePerson, MoveNet: 12.45 -> 12.20 px median reprojection error (every 4th frame;
            # +-0.15 px from sub-pixel crop changes alone), BlazePose 19.4 -> 18.5 px
            xy = xy - 0.5
            roi = None if roi is None else roi - 0.5
        return xy, sc, person, roi

    def _top_down(self, images, streams=None):
        self._pyr = {}  # pyramid levels of these images, shared by the pose passes
        try:
            if streams is None or self.config.detect_every <= 1:
                return self._top_down_passes(images)[0]
            return self._tracked(images, list(streams))
        finally:
            self._pyr = {}

    def _top_down_passes(self, images):
        boxes = self.detect(images)
        passes = self.config.refine_passes
        # the refine passes before the last only place the crops: no flip test there unless flip_all_passes
        # (the first pass keeps it: its person score is the presence gate below)
        early_flip = None if self.config.flip_all_passes else False
        res = self.pose_on_boxes(images, boxes)
        # presence is judged on the detector's box too: a refine crop zoomed onto a person-like thing raises
        # the model's score (vtest.avi's static sign: 0.23 on its box with the flip test, 0.26 refined)
        first_person = [r[2] for r in res]
        if self.config.rotation_weak > 0:
            res = self._rotation_hypotheses(images, boxes, res)
        for k_pass in range(passes):
            # again on the box the keypoints span, rotated upright: the detector's box is loose or cuts limbs,
            # and models trained on aligned crops (BlazePose) lose leaning people in unrotated crops
            t = time.perf_counter()
            ba = []
            for (xy, sc, _, roi), b in zip(res, boxes, strict=True):
                if roi is not None and self.config.model_roi:
                    ba.append((roi[:, :4], roi[:, 4]))
                else:
                    ba.append(upright_boxes(xy, sc, self.src_skeleton, b))
            self._tick("pose_post", t)
            new = self.pose_on_boxes(
                images,
                [b for b, _ in ba],
                [a if self.config.rotate else 0 * a for _, a in ba],
                self.config.tta_scales if k_pass == passes - 1 else (1.0,),
                flip=None if k_pass == passes - 1 else early_flip,
            )
            # a refined crop that slid off its detector box onto someone else (an occluded person's crop
            # centred on the person in front) keeps the previous pass's pose instead
            t = time.perf_counter()
            res = [self._keep_on_box(old, nw, b) for old, nw, b in zip(res, new, boxes, strict=True)]
            self._tick("pose_post", t)
        if self.config.duplicate_frac > 0:
            res = self._resolve_duplicates(images, boxes, res)
        return self._finish_top_down(res, boxes, first_person)

    def _finish_top_down(self, res, boxes, first_person):
        """Presence gate, back-view face rule and skeleton conversion. Returns the FrameResults and, per
        image, the kept people's ``(xy, score)`` in the model's skeleton (the next frame's crops)."""
        out, kept = [], []
        t = time.perf_counter()
        hide = self.config.hide_face_from_behind
        if hide is None:
            hide = self.pose_spec.decoder.hide_face_from_behind
        for (xy, sc, person, _), b, p0 in zip(res, boxes, first_person, strict=True):
            keep = np.minimum(person, p0) >= self.config.pose_presence
            kept.append((xy[keep], sc[keep]))
            if hide:
                sc = hide_face_from_behind(xy, sc, self.src_skeleton, self.config.back_view_facing)
            out.append(self._finish(b[keep], xy[keep], sc[keep]))
        self._tick("pose_post", t)
        return out, kept

    # ---- tracked crops: the previous frame's poses place this frame's crops
    def _tracked(self, images, streams) -> list[FrameResult]:
        """One image per stream (camera). A stream's people are cropped where its previous frame's poses
        were, and estimated by the refine passes alone (``config.track_passes``). The detector runs on a
        stream's first frame, every ``config.detect_every`` frames (people who entered), on the frame after
        a tracked person was lost (presence under ``pose_presence``, a pose that left its previous box, a
        duplicate dropped) and while the stream has nobody to track (then the pose model costs nothing)."""
        if len(set(streams)) != len(streams):
            raise ValueError(f"one image per stream per call; got streams {list(streams)}")
        every = self.config.detect_every
        detect = [
            s not in self._seeds
            or self._seeds[s].lost
            or not len(self._seeds[s].xy)
            or self._seeds[s].age + 1 >= every
            for s in streams
        ]
        out: list[FrameResult | None] = [None] * len(images)
        det_i = [i for i, d in enumerate(detect) if d]
        trk_i = [i for i, d in enumerate(detect) if not d]
        if det_i:
            res, kept = self._top_down_passes([images[i] for i in det_i])
            for i, r, (xy, sc) in zip(det_i, res, kept, strict=True):
                out[i] = r
                self._seeds[streams[i]] = _Seed(xy, sc, keypoint_boxes(xy, sc, r.boxes))
            self._pyr = {}  # the pyramid cache is keyed by list position
        if trk_i:
            seeds = [self._seeds[streams[i]] for i in trk_i]
            res, kept, lost = self._tracked_passes([images[i] for i in trk_i], seeds)
            for i, seed, r, (xy, sc), gone in zip(trk_i, seeds, res, kept, lost, strict=True):
                out[i] = r
                self._seeds[streams[i]] = _Seed(xy, sc, keypoint_boxes(xy, sc, r.boxes), seed.age + 1, gone)
        self.n_detected += len(det_i)
        self.n_tracked += len(trk_i)
        return out  # type: ignore[return-value]

    def _tracked_passes(self, images, seeds):
        t = time.perf_counter()
        boxes = [s.boxes for s in seeds]  # the previous frame's keypoint boxes
        ba = [upright_boxes(s.xy, s.sc, self.src_skeleton, s.boxes) for s in seeds]
        self._tick("pose_post", t)
        passes = max(1, self.config.track_passes)
        early_flip = None if self.config.flip_all_passes else False
        res = None
        for k_pass in range(passes):
            last = k_pass == passes - 1
            new = self.pose_on_boxes(
                images,
                [b for b, _ in ba],
                [a if self.config.rotate else 0 * a for _, a in ba],
                self.config.tta_scales if last else (1.0,),
                flip=None if last else early_flip,
            )
            t = time.perf_counter()
            res = (
                new
                if res is None
                else [self._keep_on_box(o, n, b) for o, n, b in zip(res, new, boxes, strict=True)]
            )
            if not last:
                ba = [
                    upright_boxes(xy, sc, self.src_skeleton, b)
                    for (xy, sc, _, _), b in zip(res, boxes, strict=True)
                ]
            self._tick("pose_post", t)
        t = time.perf_counter()
        # a pose that left its previous frame's box jumped (onto someone else, or lost the person)
        moved = [
            _keypoint_box_iou(xy, sc, b) < self.config.min_box_iou
            if self.config.min_box_iou > 0
            else np.zeros(len(b), bool)
            for (xy, sc, _, _), b in zip(res, boxes, strict=True)
        ]
        res = [(xy, sc, np.where(m, 0.0, p), roi) for (xy, sc, p, roi), m in zip(res, moved, strict=True)]
        self._tick("pose_post", t)
        if self.config.duplicate_frac > 0:
            res = self._resolve_duplicates(images, boxes, res)
        person = [r[2] for r in res]
        out, kept = self._finish_top_down(res, [self._kp_boxes(r) for r in res], person)
        lost = [len(k[0]) < len(b) for k, b in zip(kept, boxes, strict=True)]
        return out, kept, lost

    @staticmethod
    def _kp_boxes(r) -> np.ndarray:
        """(M,5) boxes of a pass's confident keypoints, scored by the person score."""
        xy, sc, person, _ = r
        b = keypoint_boxes(xy, sc, np.zeros((len(xy), 5)), margin=0.0)
        b[:, 4] = person
        return b

    def reset_streams(self) -> None:
        """Forget the tracked people of every stream (the next call runs the detector everywhere)."""
        self._seeds.clear()
        if self.hands is not None:
            self.hands.reset_streams()

    def _rotation_hypotheses(self, images, boxes, res):
        """People whose first-pass score is under ``config.rotation_weak`` (a body sideways or upside down:
        crop models are trained on upright people) are estimated again on the detector's box rotated by 90,
        180 and 270 degrees; the most confident of the four readings places the refine passes' crop (which
        then turns the body upright from its hips -> shoulders direction)."""
        weak = [np.flatnonzero(p < self.config.rotation_weak) for _, _, p, _ in res]
        if not sum(len(w) for w in weak):
            return res
        angs = np.deg2rad([90.0, 180.0, 270.0])
        bx = [np.repeat(b[w], len(angs), 0) for b, w in zip(boxes, weak, strict=True)]
        an = [np.tile(angs, len(w)) for w in weak]
        again = self.pose_on_boxes(images, bx, an)
        out = []
        for (xy, sc, p, roi), w, (xa, sa, pa, _) in zip(res, weak, again, strict=True):
            xy, sc, p = xy.copy(), sc.copy(), p.copy()
            for k, m in enumerate(w):
                r = slice(k * len(angs), (k + 1) * len(angs))
                best = int(np.argmax(pa[r]))
                if pa[r][best] > p[m]:
                    xy[m], sc[m], p[m] = xa[r][best], sa[r][best], pa[r][best]
            out.append((xy, sc, p, roi))
        return out

    def _resolve_duplicates(self, images, boxes, res):
        """Occluded people: where two poses a, b of one image coincide, each is estimated again on a copy of
        the image with the other's body erased (thick lines along its limbs, filled with the colour around
        it: ``_erase_body``), cropped around its own detector box. Of the two readings (a re-estimated next to
        the old b, or b next to the old a), the one that no longer coincides with the higher summed person
        score is kept: a crop model facing two overlapping people returns one pose that takes parts of both
        (Demo_MultiPerson cam03 frame 75: the face of the person behind on the body of the person in front),
        and which of the two poses is the mixed one is not known beforehand. If both still coincide, the one
        whose keypoints fit its detector box worse is dropped (person score 0) rather than counted twice.
        Each reading is made with the body erased two ways (``config.erase_fills``: background colour and the
        pad value); all of them run as one batch."""
        t = time.perf_counter()
        pairs: list[tuple[int, int, int]] = []  # (image, a, b)
        for i, ((xy, sc, _p, _), det) in enumerate(zip(res, boxes, strict=True)):
            if len(det) < 2:
                continue
            seen: set[int] = set()
            for a, b in _duplicate_pairs(xy, sc, self.config.duplicate_frac):
                if a not in seen and b not in seen:
                    pairs.append((i, a, b))
                    seen |= {a, b}
        self._tick("pose_post", t)
        if not pairs:
            return res
        t = time.perf_counter()
        fills = [None if f < 0 else f for f in self.config.erase_fills]
        imgs, bxs, which = [], [], []  # per pair, 2 x len(fills) readings in a row
        for i, a, b in pairs:
            for redo, other in ((a, b), (b, a)):
                for f in fills:
                    img = images[i].copy()
                    _erase_body(img, res[i][0][other], res[i][1][other], self.src_skeleton, f)
                    imgs.append(img)
                    bxs.append(boxes[i][redo : redo + 1])
                    which.append((redo, other))
        self._tick("crop", t)  # erasing is crop preparation (counted in the pipeline's overhead)
        saved = self._pyr
        self._pyr = {}  # the painted copies have their own pyramid levels
        try:
            again = self.pose_on_boxes(imgs, bxs)
        finally:
            self._pyr = saved
        t = time.perf_counter()
        res = [tuple(np.array(v) if v is not None else None for v in r) for r in res]
        frac = self.config.duplicate_frac
        for k, (i, a, b) in enumerate(pairs):
            xy_i, sc_i, p_i = res[i][0], res[i][1], res[i][2]
            best = None
            r = slice(k * 2 * len(fills), (k + 1) * 2 * len(fills))
            for (redo, other), (xy, sc, person, _) in zip(which[r], again[r], strict=True):
                two_xy, two_sc = np.stack([xy[0], xy_i[other]]), np.stack([sc[0], sc_i[other]])
                apart = not _duplicate_pairs(two_xy, two_sc, frac)
                total = float(person[0] + p_i[other])
                if apart and (best is None or total > best[0]):
                    best = (total, redo, xy[0], sc[0], person[0])
            if best is None:  # still the same person: drop the one that fits its box worse
                iou = _keypoint_box_iou(xy_i[[a, b]], sc_i[[a, b]], boxes[i][[a, b]])
                p_i[a if iou[0] < iou[1] else b] = 0.0
            else:
                _, redo, xy_i[redo], sc_i[redo], p_i[redo] = best
        self._tick("pose_post", t)
        return res

    def _keep_on_box(self, old, new, det: np.ndarray):
        """Per person, the new pass's result unless its confident keypoints' box overlaps the detector box
        by less than ``config.min_box_iou`` (IoU) while the old pass's did not."""
        if not len(det) or self.config.min_box_iou <= 0:
            return new
        iou_new = _keypoint_box_iou(new[0], new[1], det)
        iou_old = _keypoint_box_iou(old[0], old[1], det)
        back = (iou_new < self.config.min_box_iou) & (iou_old >= iou_new)
        if not back.any():
            return new
        out = [
            np.where(back[(slice(None),) + (None,) * (a.ndim - 1)], o, a)
            for o, a in zip(old[:3], new[:3], strict=True)
        ]
        return (*out, new[3])

    def _finish(self, boxes, xy, sc) -> FrameResult:
        if self.body_skeleton != self.src_skeleton:
            xy, sc = convert(xy, sc, self.src_skeleton, self.body_skeleton)
        xy = np.asarray(xy, np.float32)
        sc = np.asarray(sc, np.float32)
        xy[sc <= 0] = np.nan
        return FrameResult(np.asarray(boxes, np.float32), xy, sc)

    def _one_stage(self, images):
        spec = self.pose_spec
        t = time.perf_counter()
        x, ratios = self._letterbox_batch(images, spec)
        t = self._tick("detect_pre", t)
        outs = self.pose.run(x)
        t = self._tick("pose", t)
        d = spec.decoder
        if d.kind == "movenet_multipose":
            people = D.decode_movenet_multipose(outs[0], spec.input.size_wh, d.score_threshold)
        else:
            people = D.decode_rtmo(outs[0], outs[1], d.score_threshold, d.nms_iou)
        if d.pixel_coords == "corner":  # to pixel-centre coordinates, as the top-down decoders
            people = [(b, xy - 0.5, sc) for b, xy, sc in people]
        res = []
        for (b, xy, sc), r in zip(people, ratios, strict=True):
            b = b.copy()
            b[:, :4] /= r
            order = np.argsort(-b[:, 4])[: self.config.max_people]
            res.append(self._finish(b[order], xy[order] / r, sc[order]))
        self._tick("pose_post", t)
        return res

    def _bottom_up(self, images):
        spec = self.pose_spec
        d = spec.decoder
        t = time.perf_counter()
        x, ratios = self._letterbox_batch(images, spec)
        t = self._tick("detect_pre", t)
        maps = self.pose.run(x)[0]  # (B,h,w,C) (NHWC) or (B,C,h,w)
        if maps.shape[-1] != d.n_parts + 1 + 2 * len(D.OPENPOSE_LIMBS):
            maps = maps.transpose(0, 2, 3, 1)
        t = self._tick("pose", t)
        res = []
        for m, r in zip(maps, ratios, strict=True):
            boxes, xy, sc, to_img = D.people_from_maps(m, r, d)
            fr = self._finish(
                boxes[: self.config.max_people], xy[: self.config.max_people], sc[: self.config.max_people]
            )
            if self.config.keep_maps:
                fr.maps, fr.maps_to_img = m.astype(np.float16), to_img
            res.append(fr)
        self._tick("pose_post", t)
        return res
