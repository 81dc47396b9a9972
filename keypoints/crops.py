"""Crops for top-down models: model input tensors, letterboxing, affine person crops (rotated upright) and
their inverse, the boxes the next pass or frame crops from, and the image regions and pyramid levels the
crops are cut from."""

from __future__ import annotations

import cv2
import numpy as np

from roomcap.keypoints.registry import ModelSpec
from roomcap.keypoints.skeletons import get_skeleton


def to_tensor(batch: np.ndarray, spec: ModelSpec) -> np.ndarray:
    """batch (B,H,W,3) uint8 BGR -> model input (B,3,H,W) | (B,H,W,3), the description's dtype/colour."""
    s = spec.input
    if batch.ndim != 4 or batch.shape[-1] != 3:
        raise ValueError(f"to_tensor: expected (B,H,W,3) images, got {batch.shape}")
    if s.color == "RGB":  # cv2's channel swap (SIMD) is 3x numpy's reversed-stride copy here
        batch = np.stack([cv2.cvtColor(im, cv2.COLOR_BGR2RGB) for im in batch]) if len(batch) else batch
    if s.dtype == "uint8":
        x = batch
    else:
        x = batch.astype(np.float32)
        if s.scale != 1.0:
            x *= np.float32(s.scale)
        if any(s.mean):
            x -= np.asarray(s.mean, np.float32)
        if any(v != 1.0 for v in s.std):
            x /= np.asarray(s.std, np.float32)
    if s.layout == "NCHW":
        x = x.transpose(0, 3, 1, 2)
    return np.ascontiguousarray(x)


def letterbox(img: np.ndarray, size_wh: tuple[int, int], pad_value: float, out: np.ndarray | None = None):
    """Resize keeping aspect by r = min(W/w, H/h), paste at the top-left of a padded canvas (H,W,3).

    Returns (canvas, r); image px = input px / r.
    """
    h, w = img.shape[:2]
    W, H = size_wh
    r = min(W / w, H / h)
    nw, nh = max(1, int(round(w * r))), max(1, int(round(h * r)))
    canvas = np.full((H, W, 3), pad_value, np.uint8) if out is None else out
    if out is not None:
        canvas[...] = pad_value
    canvas[:nh, :nw] = cv2.resize(img, (nw, nh), interpolation=cv2.INTER_LINEAR)
    return canvas, r


def crop_transform(
    box: np.ndarray, size_wh: tuple[int, int], padding: float, angle_rad: float = 0.0
) -> np.ndarray:
    """(2,3) affine image px -> crop px for a box x0,y0,x1,y1 enlarged by ``padding`` to the crop's aspect.

    ``angle_rad``: the body's tilt from the image's up direction (clockwise positive); the crop is rotated by
    it so that the person stands upright in the crop (BlazePose's ROI alignment, mediapipe's pose landmark
    graph). The box is then taken in that rotated frame.
    """
    W, H = size_wh
    cx, cy = 0.5 * (box[0] + box[2]), 0.5 * (box[1] + box[3])
    bw, bh = (box[2] - box[0]) * padding, (box[3] - box[1]) * padding
    aspect = W / H
    if bw / max(bh, 1e-6) > aspect:
        bh = bw / aspect
    else:
        bw = bh * aspect
    s = W / max(bw, 1e-6)
    c, n = np.cos(angle_rad), np.sin(angle_rad)
    A = s * np.array([[c, n], [-n, c]])  # rotate the image by -angle, then scale
    return np.hstack([A, (np.array([W / 2, H / 2]) - A @ np.array([cx, cy]))[:, None]])


def apply_inverse(M: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Crop px back to image px through the inverse of affines M (N,2,3); xy (N,J,2)."""
    A, t = M[:, :, :2], M[:, :, 2]
    Ainv = np.linalg.inv(A)  # (N,2,2)
    return np.einsum("nij,nkj->nki", Ainv, xy - t[:, None, :])


def upright_boxes(
    xy: np.ndarray,
    sc: np.ndarray,
    skeleton: str,
    det: np.ndarray,
    min_score: float = 0.3,
    margin: float = 0.1,
):
    """Boxes (M,4) and tilt angles (M,) from first-pass keypoints (M,J,2) image px, scores (M,J).

    The tilt is the angle of the hips-centre -> shoulders-centre vector from the image's up direction; the
    box is the extent of the confident keypoints in the frame rotated upright, grown by ``margin`` x its
    size (keypoints are joint centres: head top and feet lie beyond them). Where fewer than 4 keypoints or
    no hips/shoulders are confident, the detector's box and no tilt.
    """
    sk = get_skeleton(skeleton)
    try:
        idx = [sk.index(n) for n in ("left_hip", "right_hip", "left_shoulder", "right_shoulder")]
    except KeyError:
        idx = None
    boxes = np.asarray(det[:, :4], np.float64).copy()
    angles = np.zeros(len(det))
    for i in range(len(det)):
        ok = sc[i] >= min_score
        if ok.sum() < 4:
            continue
        p = xy[i, ok].astype(np.float64)
        a = 0.0
        if idx is not None and (sc[i, idx] >= min_score).all():
            hip = 0.5 * (xy[i, idx[0]] + xy[i, idx[1]])
            sho = 0.5 * (xy[i, idx[2]] + xy[i, idx[3]])
            up = sho - hip
            a = float(np.arctan2(up[0], -up[1]))  # 0 = upright, clockwise positive
        c, n = np.cos(a), np.sin(a)
        R = np.array([[c, n], [-n, c]])
        q = p @ R.T  # rotated frame
        lo, hi = q.min(0), q.max(0)
        m = margin * max(hi - lo)
        lo, hi = lo - m, hi + m
        ctr = R.T @ (0.5 * (lo + hi))  # back to image frame
        half = 0.5 * (hi - lo)
        boxes[i] = (ctr[0] - half[0], ctr[1] - half[1], ctr[0] + half[0], ctr[1] + half[1])
        angles[i] = a
    return boxes, angles


def keypoint_boxes(
    xy: np.ndarray, sc: np.ndarray, fallback: np.ndarray, margin: float = 0.1, min_score: float = 0.3
) -> np.ndarray:
    """(M,5) axis-aligned boxes of each person's confident keypoints xy (M,J,2), scores (M,J), grown by
    ``margin`` x the larger side; ``fallback`` (M,>=4) where fewer than 2 keypoints are confident. Column 4
    is the fallback's score."""
    out = np.zeros((len(xy), 5))
    if len(fallback):
        out[:, : min(5, fallback.shape[1])] = np.asarray(fallback, np.float64)[:, :5]
    for i in range(len(xy)):
        ok = (sc[i] >= min_score) & np.isfinite(xy[i, :, 0])
        if ok.sum() < 2:
            continue
        lo, hi = xy[i, ok].min(0), xy[i, ok].max(0)
        m = margin * float(max(hi - lo))
        out[i, :4] = (lo[0] - m, lo[1] - m, hi[0] + m, hi[1] + m)
    return out


PYRAMIDS = ("gaussian", "box", "mixed")


def level_offset(levels: int, pyramid: str) -> float:
    """Image px of a level's pixel 0 (x = 2^L x_L + c): 0 for pyrDown (its kernel is centred on pixel 2i),
    (2^L - 1) / 2 for 2x2 means (a level-L pixel is the mean of image pixels 2^L x_L .. 2^L x_L + 2^L - 1),
    and for "mixed" the box levels' offset (2^(L-1) - 1) / 2, which the last level's pyrDown keeps."""
    if pyramid == "box":
        return (2**levels - 1) / 2
    if pyramid == "mixed" and levels > 1:
        return (2 ** (levels - 1) - 1) / 2
    return 0.0


def crop_region(M: np.ndarray, size_wh: tuple[int, int], shape, f: int) -> tuple[int, int, int, int]:
    """Image px region x0,y0,x1,y1 that a crop of affine M (image -> crop px) samples, with a margin of 4f
    px (the reach of L = log2 f pyrDown kernels, 2(f - 1), and of the bilinear sample at level L), clipped
    to the image, its corner on multiples of f."""
    W, H = size_wh
    corners = np.array([[0.0, 0.0], [W, 0.0], [0.0, H], [W, H]])
    A, t = M[:, :2], M[:, 2]
    xy = (corners - t) @ np.linalg.inv(A).T
    h, w = shape[:2]
    m = 4 * f
    x0 = int(np.clip(np.floor(xy[:, 0].min()) - m, 0, w - 1)) // f * f
    y0 = int(np.clip(np.floor(xy[:, 1].min()) - m, 0, h - 1)) // f * f
    x1 = int(np.clip(np.ceil(xy[:, 0].max()) + m + 1, x0 + 1, w))
    y1 = int(np.clip(np.ceil(xy[:, 1].max()) + m + 1, y0 + 1, h))
    return x0, y0, x1, y1


def containing_region(regions, box):
    """The first region (x0, y0, x1, y1, level) that contains box x0,y0,x1,y1, else None."""
    return next(
        (r for r in regions if r[0] <= box[0] and r[1] <= box[1] and r[2] >= box[2] and r[3] >= box[3]), None
    )
