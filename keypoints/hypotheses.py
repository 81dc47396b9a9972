"""Hypotheses of one person's pose and how the pipeline settles them: test-time augmentation merges (flip,
crop sizes), the back-view face rule, weak boxes, coinciding poses and erasing a person from the image."""

from __future__ import annotations

import cv2
import numpy as np

from roomcap.keypoints.skeletons import get_skeleton

FACE_POINTS = ("nose", "left_eye", "right_eye", "mouth")  # name prefixes (eye_inner/outer, mouth_left, ...)


def facing(xy: np.ndarray, sc: np.ndarray, skeleton: str, min_score: float = 0.3) -> np.ndarray:
    """How much each person (M,J,2) faces the camera: the mean of the signed shoulder and hip widths
    (left minus right joint along the body's own horizontal, image px) over the hips-centre ->
    shoulders-centre length; NaN where the four joints are not all confident.

    A person facing the camera has the left shoulder and hip on the image's right (positive); from behind the
    sign flips (COCO-style models label left/right by the body, not the image). For an adult the value is
    about 0.5 x cos(yaw) (shoulder width ~0.6 and hip width ~0.35 x torso length), whatever the image scale.
    """
    sk = get_skeleton(skeleton)
    try:
        ls, rs, lh, rh = (sk.index(n) for n in ("left_shoulder", "right_shoulder", "left_hip", "right_hip"))
    except KeyError:
        return np.full(len(xy), np.nan)
    xy = np.asarray(xy, np.float64)
    up = 0.5 * (xy[:, ls] + xy[:, rs]) - 0.5 * (xy[:, lh] + xy[:, rh])  # (M,2)
    length = np.linalg.norm(up, axis=-1)
    right = np.stack([-up[:, 1], up[:, 0]], -1) / np.maximum(length, 1e-9)[:, None]  # body's horizontal
    w = np.einsum("mi,mi->m", xy[:, ls] - xy[:, rs] + xy[:, lh] - xy[:, rh], right)
    f = 0.5 * w / np.maximum(length, 1e-9)
    ok = (np.asarray(sc)[:, [ls, rs, lh, rh]] >= min_score).all(1) & (length > 1.0) & np.isfinite(f)
    return np.where(ok, f, np.nan)


def hide_face_from_behind(
    xy: np.ndarray, sc: np.ndarray, skeleton: str, threshold: float = -0.15
) -> np.ndarray:
    """Scores (M,J) with the face points (nose, eyes, mouth; not the ears) set to 0 for people whose
    ``facing`` is below ``threshold`` (turned away from the camera by more than about 107 degrees).

    Single-person crop models (MoveNet) place these points with the confidence of the visible joints on the
    back of a head; triangulated, they pull the 3D nose and eyes off and add 15-25 px reprojection error in
    every view (Demo_SinglePerson). OpenPose gives them low scores instead. The head turning away from the
    torso is not seen by this rule.
    """
    sk = get_skeleton(skeleton)
    face = [j for j, n in enumerate(sk.joint_names) if n.startswith(FACE_POINTS)]
    sc = np.array(sc, copy=True)
    if not face or not len(sc):
        return sc
    back = facing(xy, sc, skeleton) < threshold
    sc[np.ix_(back, face)] = 0.0
    return sc


def _strong_or_apart(boxes: np.ndarray, threshold: float, max_inside: float = 0.5) -> np.ndarray:
    """Mask (N,) of boxes (N,5) scoring >= ``threshold``, or weaker ones of which less than ``max_inside`` of
    the area lies inside any box scoring higher."""
    keep = boxes[:, 4] >= threshold
    for i in np.flatnonzero(~keep):
        b = boxes[i]
        higher = boxes[boxes[:, 4] > b[4]]
        iw = np.clip(np.minimum(higher[:, 2], b[2]) - np.maximum(higher[:, 0], b[0]), 0, None)
        ih = np.clip(np.minimum(higher[:, 3], b[3]) - np.maximum(higher[:, 1], b[1]), 0, None)
        area = max((b[2] - b[0]) * (b[3] - b[1]), 1e-9)
        keep[i] = not len(higher) or (iw * ih).max() < max_inside * area
    return keep


def merge_hypotheses(xy0, sc0, xy1, sc1, tol: float):
    """Two estimates of the same people's joints (M,J,2) with scores (M,J) -> one (test-time augmentation).

    Joints the two place within ``tol`` px of each other: the score-weighted mean (and the mean score).
    Joints they place apart are two different answers (a leg taken for the other, a limb of someone
    behind), whose mean would lie on neither: per person, all of them come from the estimate with the higher
    mean score over those joints (one hypothesis, so a left/right pair is not split between the two).
    ``tol`` <= 0: always the weighted mean.
    """
    w0, w1 = sc0[..., None] + 1e-6, sc1[..., None] + 1e-6
    xy = (xy0 * w0 + xy1 * w1) / (w0 + w1)
    sc = 0.5 * (sc0 + sc1)
    if tol <= 0:
        return xy, sc
    apart = np.linalg.norm(xy0 - xy1, axis=-1) > tol  # (M,J)
    n = np.maximum(apart.sum(1), 1)
    first = (np.where(apart, sc0, 0).sum(1) / n) >= (np.where(apart, sc1, 0).sum(1) / n)  # (M,)
    pick_xy = np.where(first[:, None, None], xy0, xy1)
    pick_sc = np.where(first[:, None], sc0, sc1)
    return np.where(apart[..., None], pick_xy, xy), np.where(apart, pick_sc, sc)


def consensus(xy: np.ndarray, sc: np.ndarray, tol) -> tuple[np.ndarray, np.ndarray]:
    """K estimates (K,M,J,2), scores (K,M,J) of the same joints -> one (M,J,2), (M,J): the score-weighted
    mean of the estimates within ``tol`` px (scalar or broadcasting to (M,J)) of the coordinate-wise median,
    with their mean score; an estimate far from the others is left out rather than averaged in."""
    med = np.median(xy, axis=0)
    inl = np.linalg.norm(xy - med, axis=-1) <= np.asarray(tol)  # (K,M,J)
    none = ~inl.any(0)
    inl[:, none] = sc[:, none] == sc[:, none].max(0)  # all apart: the most confident
    w = np.where(inl, sc + 1e-6, 0.0)
    out = (xy * w[..., None]).sum(0) / w.sum(0)[..., None]
    return out, (sc * inl).sum(0) / inl.sum(0)


def _keypoint_box_iou(xy: np.ndarray, sc: np.ndarray, det: np.ndarray, min_score: float = 0.3) -> np.ndarray:
    """IoU (M,) of the box of each person's confident keypoints (M,J,2) with its box det (M,>=4)."""
    out = np.zeros(len(det))
    for i in range(len(det)):
        ok = (sc[i] >= min_score) & np.isfinite(xy[i, :, 0])
        if ok.sum() < 2:
            continue
        (x0, y0), (x1, y1) = xy[i, ok].min(0), xy[i, ok].max(0)
        b = det[i]
        iw = max(0.0, min(x1, b[2]) - max(x0, b[0]))
        ih = max(0.0, min(y1, b[3]) - max(y0, b[1]))
        inter = iw * ih
        union = (x1 - x0) * (y1 - y0) + (b[2] - b[0]) * (b[3] - b[1]) - inter
        out[i] = inter / max(union, 1e-9)
    return out


def _duplicate_pairs(
    xy: np.ndarray, sc: np.ndarray, frac: float, min_score: float = 0.3, min_joints: int = 4
):
    """Pairs (a, b) of poses xy (M,J,2), sc (M,J) whose median joint distance over the joints both see
    confidently is under ``frac`` x the larger side of the smaller pose's keypoint box."""
    out = []
    ok = (sc >= min_score) & np.isfinite(xy[..., 0])
    size = np.zeros(len(xy))
    for m in range(len(xy)):
        if ok[m].sum() >= 2:
            size[m] = (xy[m, ok[m]].max(0) - xy[m, ok[m]].min(0)).max()
    for a in range(len(xy)):
        for b in range(a + 1, len(xy)):
            both = ok[a] & ok[b]
            if both.sum() < min_joints:
                continue
            d = np.median(np.linalg.norm(xy[a, both] - xy[b, both], axis=-1))
            if d < frac * min(size[a], size[b]):
                out.append((a, b))
    return out


def _paint_body(
    img: np.ndarray,
    xy: np.ndarray,
    sc: np.ndarray,
    skeleton: str,
    value: float,
    min_score: float = 0.3,
    width: float = 0.12,
) -> None:
    """Paint a person over in place: lines ``width`` x the keypoint box height thick along the limbs between
    confident keypoints xy (J,2), and discs at them (the torso as a filled polygon)."""
    sk = get_skeleton(skeleton)
    ok = (sc >= min_score) & np.isfinite(xy[:, 0])
    if ok.sum() < 2:
        return
    h = float(np.ptp(xy[ok, 1]))
    th = max(2, int(round(width * h)))
    col = (int(value),) * 3
    for a, b in sk.limbs:
        if ok[a] and ok[b]:
            cv2.line(img, tuple(int(v) for v in xy[a]), tuple(int(v) for v in xy[b]), col, th)
    for j in np.flatnonzero(ok):
        cv2.circle(img, tuple(int(v) for v in xy[j]), th // 2 + 1, col, -1)
    try:
        torso = [sk.index(n) for n in ("left_shoulder", "right_shoulder", "right_hip", "left_hip")]
    except KeyError:
        return
    if ok[torso].all():
        cv2.fillConvexPoly(img, np.round(xy[torso]).astype(np.int32), col)


def _erase_body(
    img: np.ndarray,
    xy: np.ndarray,
    sc: np.ndarray,
    skeleton: str,
    fill: float | None = None,
    ring: float = 0.05,
) -> None:
    """Erase a person in place: the ``_paint_body`` mask filled with ``fill`` (a grey value) or, for None,
    with the median colour of a ring around it (``ring`` x the keypoint box height wide): the background's
    colour. A black person-shaped silhouette is itself taken for a person by crop models (Demo_MultiPerson
    cam03 frames 75 and 85: the occluded person's crop re-estimated on the black silhouette of the person in
    front), while on others the black shape reads as an occluder and the background-coloured one does not
    (frame 63); ``_resolve_duplicates`` tries both."""
    if fill is not None:
        _paint_body(img, xy, sc, skeleton, fill)
        return
    mask = np.zeros(img.shape[:2], np.uint8)
    _paint_body(mask, xy, sc, skeleton, 255)
    if not mask.any():
        return
    ok = (sc >= 0.3) & np.isfinite(xy[:, 0])
    k = 2 * max(2, int(round(ring * float(np.ptp(xy[ok, 1]))))) + 1
    around = (cv2.dilate(mask, np.ones((k, k), np.uint8)) > 0) & (mask == 0)
    m = mask > 0
    img[m] = np.median(img[around], axis=0) if around.any() else 0
