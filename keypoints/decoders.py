"""Output decoders: raw model outputs -> boxes / keypoints in the model's input pixels.

Pure numpy functions, one per output convention, each stating its shapes:

- ``decode_yolox``: YOLOX grid head (cx, cy, w, h, obj, classes) per anchor point at strides 8/16/32
  (``xy = (raw_xy + grid) * stride``, ``wh = exp(raw_wh) * stride``, score = obj x class), then NMS;
- ``decode_dets``: mmdeploy end2end detectors with NMS inside (``dets`` (B,N,5), ``labels`` (B,N));
- ``decode_blazepose``: 39 x (x, y, z, visibility, presence) in crop pixels, logits -> sigmoid;
- ``decode_movenet``: (B,1,17,3) = (y, x, score) normalised to the input;
- ``decode_simcc``: RTMPose x / y logits over bins at ``split_ratio`` x the input resolution;
- ``decode_rtmo``: one-stage boxes + keypoints (``dets`` (B,N,5), ``keypoints`` (B,N,J,3));
- ``find_peaks`` + ``group_paf``: OpenPose confidence-map peaks and part-affinity-field grouping
  (Cao et al. 2017, the 2D detector the seed's ch. 4/5 trackers consume).
"""

from __future__ import annotations

import cv2
import numpy as np

# ----------------------------------------------------------------------------- boxes


def nms(boxes: np.ndarray, scores: np.ndarray, iou: float) -> np.ndarray:
    """Greedy non-maximum suppression. boxes (N,4) x0,y0,x1,y1; scores (N,). Returns kept indices (K,)."""
    if len(boxes) == 0:
        return np.zeros(0, dtype=np.int64)
    x0, y0, x1, y1 = boxes.T
    area = np.maximum(x1 - x0, 0) * np.maximum(y1 - y0, 0)
    order = np.argsort(-scores, kind="stable")
    keep = []
    while len(order):
        i = order[0]
        keep.append(i)
        rest = order[1:]
        w = np.clip(np.minimum(x1[i], x1[rest]) - np.maximum(x0[i], x0[rest]), 0, None)
        h = np.clip(np.minimum(y1[i], y1[rest]) - np.maximum(y0[i], y0[rest]), 0, None)
        inter = w * h
        union = area[i] + area[rest] - inter
        order = rest[inter <= iou * np.maximum(union, 1e-9)]
    return np.asarray(keep, dtype=np.int64)


_GRIDS: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}


def _yolox_grid(size_wh: tuple[int, int], strides: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
    key = (tuple(size_wh), tuple(strides))
    if key not in _GRIDS:
        grids, st = [], []
        w, h = size_wh
        for s in strides:
            gy, gx = np.mgrid[0 : h // s, 0 : w // s]
            grids.append(np.stack([gx.ravel(), gy.ravel()], 1))
            st.append(np.full((gx.size, 1), s))
        _GRIDS[key] = (np.concatenate(grids).astype(np.float32), np.concatenate(st).astype(np.float32))
    return _GRIDS[key]


def decode_yolox(
    raw: np.ndarray,
    size_wh: tuple[int, int],
    strides=(8, 16, 32),
    class_id: int = 0,
    score_threshold: float = 0.3,
    nms_iou: float = 0.45,
) -> list[np.ndarray]:
    """raw (B,N,5+C) -> per image (M,5) boxes x0,y0,x1,y1,score in input pixels (after NMS)."""
    raw = np.asarray(raw, dtype=np.float32)
    grid, stride = _yolox_grid(size_wh, strides)
    if raw.ndim != 3 or raw.shape[1] != len(grid) or raw.shape[2] < 6:
        raise ValueError(
            f"decode_yolox: expected (B,{len(grid)},5+C) for input {size_wh} and strides "
            f"{tuple(strides)}, got {raw.shape}"
        )
    out = []
    for r in raw:
        score = r[:, 4] * r[:, 5 + class_id]
        keep = score > score_threshold
        if not keep.any():
            out.append(np.zeros((0, 5), np.float32))
            continue
        r, s, g, st = r[keep], score[keep], grid[keep], stride[keep]
        xy = (r[:, :2] + g) * st
        wh = np.exp(np.minimum(r[:, 2:4], 20.0)) * st
        boxes = np.concatenate([xy - wh / 2, xy + wh / 2], 1)
        k = nms(boxes, s, nms_iou)
        out.append(np.concatenate([boxes[k], s[k, None]], 1).astype(np.float32))
    return out


def decode_dets(
    dets: np.ndarray,
    labels: np.ndarray | None,
    class_id: int = 0,
    score_threshold: float = 0.3,
    nms_iou: float = 0.45,
) -> list[np.ndarray]:
    """dets (B,N,5) x0,y0,x1,y1,score and labels (B,N) -> per image (M,5) person boxes in input pixels."""
    dets = np.asarray(dets, dtype=np.float32)
    if dets.ndim != 3 or dets.shape[2] != 5:
        raise ValueError(f"decode_dets: expected dets (B,N,5), got {dets.shape}")
    out = []
    for b, d in enumerate(dets):
        keep = d[:, 4] > score_threshold
        if labels is not None:
            keep &= np.asarray(labels[b]) == class_id
        d = d[keep]
        out.append(d[nms(d[:, :4], d[:, 4], nms_iou)])
    return out


# ----------------------------------------------------------------------------- single-person crops


def _sigmoid(x: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-np.clip(x, -50, 50)))


def decode_blazepose(landmarks: np.ndarray, presence: np.ndarray, n_landmarks: int = 33):
    """landmarks (B,39*5), presence (B,1) logits -> xy (B,L,2) crop px, score (B,L), person (B,), aux (B,A,2).

    Per-landmark score = sigmoid(visibility) x sigmoid(presence) (mediapipe's two per-landmark
    probabilities: visible and inside the image); ``person`` = sigmoid of the person-present logit;
    ``aux``: the auxiliary landmarks after the body ones (crop px); the first two are mediapipe's ROI
    alignment points (hip centre, and a point above the head at the full-body radius).
    """
    landmarks = np.asarray(landmarks, dtype=np.float32)
    if landmarks.ndim != 2 or landmarks.shape[1] % 5:
        raise ValueError(f"decode_blazepose: expected (B,5*L) landmarks, got {landmarks.shape}")
    full = landmarks.reshape(len(landmarks), -1, 5)
    lm = full[:, :n_landmarks]
    score = _sigmoid(lm[..., 3]) * _sigmoid(lm[..., 4])
    person = _sigmoid(np.asarray(presence, dtype=np.float32).reshape(len(lm), -1)[:, 0])
    return lm[..., :2].copy(), score, person, full[:, n_landmarks:, :2].copy()


def decode_movenet(out: np.ndarray, size_wh: tuple[int, int]):
    """out (B,1,J,3) = (y, x, score) in [0,1] -> xy (B,J,2) input px, score (B,J)."""
    out = np.asarray(out, dtype=np.float32)
    if out.ndim != 4 or out.shape[-1] != 3:
        raise ValueError(f"decode_movenet: expected (B,1,J,3), got {out.shape}")
    o = out[:, 0]
    xy = np.stack([o[..., 1] * size_wh[0], o[..., 0] * size_wh[1]], -1)
    return xy, o[..., 2]


def decode_simcc(simcc_x: np.ndarray, simcc_y: np.ndarray, split_ratio: float = 2.0):
    """simcc_x (B,J,Wx), simcc_y (B,J,Hy) -> xy (B,J,2) input px, score (B,J) in [0,1].

    RTMPose (Jiang et al. 2023): the keypoint is the arg-max bin / split_ratio; its score the smaller of
    the two maxima (as rtmlib's ``get_simcc_maximum``), clipped to [0, 1].
    """
    sx, sy = np.asarray(simcc_x), np.asarray(simcc_y)
    if sx.ndim != 3 or sy.ndim != 3 or sx.shape[:2] != sy.shape[:2]:
        raise ValueError(f"decode_simcc: expected (B,J,Wx) and (B,J,Hy), got {sx.shape} and {sy.shape}")
    ix, iy = sx.argmax(-1), sy.argmax(-1)
    vx, vy = sx.max(-1), sy.max(-1)
    xy = np.stack([ix, iy], -1).astype(np.float32) / split_ratio
    return xy, np.clip(np.minimum(vx, vy), 0.0, 1.0)


def decode_rtmo(dets: np.ndarray, keypoints: np.ndarray, score_threshold: float = 0.5, nms_iou: float = 0.45):
    """dets (B,N,5), keypoints (B,N,J,3) -> per image (boxes (M,5), xy (M,J,2), score (M,J)) in input px."""
    dets, kp = np.asarray(dets, np.float32), np.asarray(keypoints, np.float32)
    if dets.ndim != 3 or kp.ndim != 4 or dets.shape[:2] != kp.shape[:2] or kp.shape[-1] != 3:
        raise ValueError(
            f"decode_rtmo: expected dets (B,N,5) and keypoints (B,N,J,3), got {dets.shape}, {kp.shape}"
        )
    out = []
    for d, k in zip(dets, kp, strict=True):
        keep = np.flatnonzero(d[:, 4] > score_threshold)
        keep = keep[nms(d[keep, :4], d[keep, 4], nms_iou)]
        out.append((d[keep], k[keep, :, :2], np.clip(k[keep, :, 2], 0, 1)))
    return out


def decode_movenet_multipose(out: np.ndarray, size_wh: tuple[int, int], score_threshold: float = 0.2):
    """MoveNet MultiPose ``output_0`` (B,6,56): per candidate 17 x (y, x, score) normalised to the input, then
    a box (ymin, xmin, ymax, xmax, score) -> per image (boxes (M,5) x0,y0,x1,y1,score, xy (M,17,2), score
    (M,17)) in input px, candidates whose box score exceeds ``score_threshold``."""
    out = np.asarray(out, np.float32)
    if out.ndim != 3 or out.shape[-1] != 56:
        raise ValueError(f"decode_movenet_multipose: expected (B,N,56), got {out.shape}")
    W, H = size_wh
    res = []
    for o in out:
        o = o[o[:, 55] > score_threshold]
        k = o[:, :51].reshape(-1, 17, 3)
        xy = np.stack([k[..., 1] * W, k[..., 0] * H], -1)
        b = o[:, 51:55]
        boxes = np.stack([b[:, 1] * W, b[:, 0] * H, b[:, 3] * W, b[:, 2] * H, o[:, 55]], -1)
        res.append((boxes, xy, k[..., 2]))
    return res


# ----------------------------------------------------------------------------- OpenPose (bottom-up)

# COCO-18 limbs of the PAF channels (README of the shipped model; OpenPose's order).
OPENPOSE_LIMBS = (
    (1, 2),
    (1, 5),
    (2, 3),
    (3, 4),
    (5, 6),
    (6, 7),
    (1, 8),
    (8, 9),
    (9, 10),
    (1, 11),
    (11, 12),
    (12, 13),
    (1, 0),
    (0, 14),
    (14, 16),
    (0, 15),
    (15, 17),
    (2, 16),
    (5, 17),
)


def find_peaks(heatmaps: np.ndarray, threshold: float = 0.1, sigma: float = 1.0) -> list[np.ndarray]:
    """heatmaps (H,W,P) -> per part (K,3) peaks x, y (map px, sub-pixel), score. Local maxima over 3x3."""
    hm = np.asarray(heatmaps, dtype=np.float32)
    if hm.ndim != 3:
        raise ValueError(f"find_peaks: expected (H,W,P), got {hm.shape}")
    smooth = cv2.GaussianBlur(hm, (0, 0), sigma) if sigma > 0 else hm
    if smooth.ndim == 2:
        smooth = smooth[..., None]
    pad = np.pad(smooth, ((1, 1), (1, 1), (0, 0)), constant_values=-np.inf)
    H, W = hm.shape[:2]
    neigh = np.stack(
        [pad[1 + dy : 1 + dy + H, 1 + dx : 1 + dx + W] for dy in (-1, 0, 1) for dx in (-1, 0, 1) if dy or dx]
    )
    is_peak = (smooth >= neigh.max(0)) & (smooth > threshold)
    out = []
    for p in range(hm.shape[2]):
        ys, xs = np.nonzero(is_peak[..., p])
        peaks = np.zeros((len(ys), 3), np.float32)
        for i, (y, x) in enumerate(zip(ys, xs, strict=True)):
            # quadratic sub-pixel refinement along each axis
            dx = dy = 0.0
            if 0 < x < W - 1:
                a, b, c = smooth[y, x - 1, p], smooth[y, x, p], smooth[y, x + 1, p]
                den = a - 2 * b + c
                dx = 0.5 * (a - c) / den if den < 0 else 0.0
            if 0 < y < H - 1:
                a, b, c = smooth[y - 1, x, p], smooth[y, x, p], smooth[y + 1, x, p]
                den = a - 2 * b + c
                dy = 0.5 * (a - c) / den if den < 0 else 0.0
            peaks[i] = (x + np.clip(dx, -0.5, 0.5), y + np.clip(dy, -0.5, 0.5), hm[y, x, p])
        out.append(peaks)
    return out


def _bilinear(img: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    H, W = img.shape[:2]
    x = np.clip(x, 0, W - 1.001)
    y = np.clip(y, 0, H - 1.001)
    x0, y0 = x.astype(int), y.astype(int)
    fx, fy = (x - x0)[..., None], (y - y0)[..., None]
    v = (
        img[y0, x0] * (1 - fx) * (1 - fy)
        + img[y0, x0 + 1] * fx * (1 - fy)
        + img[y0 + 1, x0] * (1 - fx) * fy
        + img[y0 + 1, x0 + 1] * fx * fy
    )
    return v


def group_paf(
    peaks: list[np.ndarray],
    pafs: np.ndarray,
    limbs=OPENPOSE_LIMBS,
    paf_threshold: float = 0.05,
    n_samples: int = 10,
    min_parts: int = 3,
    min_mean_score: float = 0.2,
):
    """Assemble people from part peaks with part affinity fields (Cao et al. 2017, sec. 2.3-2.4).

    peaks: per part (K_p,3) x, y, score in map px; pafs (H,W,2L) x/y field per limb.
    Returns xy (P,J,2) map px (NaN = missing) and score (P,J), people sorted by total score.
    """
    n_parts = len(peaks)
    pafs = np.asarray(pafs, dtype=np.float32)
    if pafs.ndim != 3 or pafs.shape[2] != 2 * len(limbs):
        raise ValueError(f"group_paf: expected pafs (H,W,{2 * len(limbs)}), got {pafs.shape}")
    H = pafs.shape[0]
    # global ids of every peak
    offsets = np.cumsum([0] + [len(p) for p in peaks])
    all_peaks = np.concatenate([p for p in peaks] + [np.zeros((0, 3), np.float32)])
    people: list[np.ndarray] = []  # rows: n_parts peak ids (-1), then total score, n parts
    t = np.linspace(0, 1, n_samples)
    for k, (a, b) in enumerate(limbs):
        pa, pb = peaks[a], peaks[b]
        if not len(pa) or not len(pb):
            continue
        field = pafs[..., 2 * k : 2 * k + 2]
        cands = _limb_candidates(pa, pb, field, t, H, paf_threshold)
        people = _join_limb(people, cands, a, b, offsets, all_peaks, n_parts)
    people = [r for r in people if r[-1] >= min_parts and r[-2] / r[-1] >= min_mean_score]
    people.sort(key=lambda r: -r[-2])
    xy = np.full((len(people), n_parts, 2), np.nan, np.float32)
    sc = np.zeros((len(people), n_parts), np.float32)
    for p, r in enumerate(people):
        ids = r[:n_parts].astype(int)
        ok = ids >= 0
        xy[p, ok] = all_peaks[ids[ok], :2]
        sc[p, ok] = all_peaks[ids[ok], 2]
    # single peaks not used by any person are dropped (a lone part is not a person)
    return xy, np.clip(sc, 0, 1)


def _limb_candidates(
    pa: np.ndarray, pb: np.ndarray, field: np.ndarray, t: np.ndarray, H: int, paf_threshold: float
) -> list[tuple[float, int, int]]:
    """The (score, i, j) connections of peak i of part a to peak j of part b that the limb's field
    supports (the field along the segment sampled at ``t``, with a distance prior), best first."""
    cands = []
    for i in range(len(pa)):
        d = pb[:, :2] - pa[i, :2]  # (Kb,2)
        norm = np.linalg.norm(d, axis=1) + 1e-6
        u = d / norm[:, None]
        xs = pa[i, 0] + t[None, :] * d[:, 0:1]
        ys = pa[i, 1] + t[None, :] * d[:, 1:2]
        v = _bilinear(field, xs, ys)  # (Kb,S,2)
        dots = (v * u[:, None, :]).sum(-1)
        score = dots.mean(1) + np.minimum(0.5 * H / norm - 1, 0)
        ok = ((dots > paf_threshold).mean(1) > 0.8) & (score > 0)
        for j in np.flatnonzero(ok):
            cands.append((score[j], i, j))
    cands.sort(key=lambda c: -c[0])
    return cands


def _join_limb(
    people: list[np.ndarray],
    cands: list[tuple[float, int, int]],
    a: int,
    b: int,
    offsets: np.ndarray,
    all_peaks: np.ndarray,
    n_parts: int,
) -> list[np.ndarray]:
    """Add one limb's connections to the people (each peak used once, greedily by score): extend the
    person holding one end, merge two disjoint people, or start a new one; the updated people."""
    used_a, used_b = set(), set()
    for s, i, j in cands:
        if i in used_a or j in used_b:
            continue
        used_a.add(i)
        used_b.add(j)
        ga, gb = offsets[a] + i, offsets[b] + j
        found = [r for r in people if r[a] == ga or r[b] == gb]
        if len(found) == 1:
            r = found[0]
            if r[b] != gb and r[b] < 0:
                r[b] = gb
                r[-1] += 1
                r[-2] += all_peaks[gb, 2] + s
            elif r[a] < 0:
                r[a] = ga
                r[-1] += 1
                r[-2] += all_peaks[ga, 2] + s
        elif len(found) == 2:
            r1, r2 = found
            if not ((r1[:n_parts] >= 0) & (r2[:n_parts] >= 0)).any():  # disjoint: merge
                r1[:n_parts] += r2[:n_parts] + 1
                r1[-2:] += r2[-2:]
                r1[-2] += s
                people = [r for r in people if r is not r2]
            else:
                if r1[b] < 0:
                    r1[b] = gb
                    r1[-1] += 1
                    r1[-2] += all_peaks[gb, 2] + s
        else:
            row = -np.ones(n_parts + 2)
            row[a], row[b] = ga, gb
            row[-1] = 2
            row[-2] = all_peaks[ga, 2] + all_peaks[gb, 2] + s
            people.append(row)
    return people


def people_from_maps(
    maps: np.ndarray, ratio: float, d
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Bottom-up: the people of one image from its confidence maps and PAFs ``maps`` (h,w,C) (the model's
    input was the image letterboxed by ``ratio``; ``d`` the description's decoder settings). Returns boxes
    (P,5) x0,y0,x1,y1,mean score, xy (P,J,2) image px, score (P,J) and the (2,3) map -> image affine."""
    heat, paf = maps[..., : d.n_parts], maps[..., d.n_parts + 1 :]
    if d.paf_channels:
        paf = paf[..., [c for pair in d.paf_channels for c in pair]]
    peaks = find_peaks(heat, d.peak_threshold)
    xy, sc = group_paf(peaks, paf, OPENPOSE_LIMBS, d.paf_threshold)
    # map px -> input px (pixel centres: (x + 0.5) * stride - 0.5) -> image px
    s, r = d.stride, ratio
    to_img = np.array([[s / r, 0, (0.5 * s - 0.5) / r], [0, s / r, (0.5 * s - 0.5) / r]])
    xy = xy * (s / r) + (0.5 * s - 0.5) / r
    boxes = np.full((len(xy), 5), np.nan, np.float32)
    for p in range(len(xy)):
        ok = ~np.isnan(xy[p, :, 0])
        if ok.any():
            boxes[p, :2], boxes[p, 2:4] = xy[p, ok].min(0), xy[p, ok].max(0)
            boxes[p, 4] = sc[p, ok].mean()
    return boxes, xy, sc, to_img
