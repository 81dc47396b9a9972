"""Observation model p(o_t | z_t) and the update step's sampling (seed ch. 5.2.2, eq. 5.6–5.8) in numpy.

The filter runs the hot chains of this module as compiled kernels (:mod:`roomcap.track.kernels`); these numpy
functions are their reference, and the maps path (eq. 5.8 on confidence maps) and the exact output
weights use them directly. :func:`associate` computes its cost table with the compiled kernel.

Shapes: K tracks, N samples per track, J joints, L limbs, C cameras, V camera
pairs, D detections per camera, M refinement candidates.

The per-camera, per-limb score phi(c, l, s) of eq. 5.8 comes from one of two
sources:

- **keypoints + scores** (every 2D model): each track is associated with at
  most one detection per camera (:func:`associate`); the joint's "confidence
  map" is that detection's keypoint as a Gaussian peak,
  ``conf = score * exp(-d^2 / 2 sigma^2)`` with ``sigma^2 = (sigma_m f / depth)^2
  + sigma_px^2`` (a metric tolerance seen at the sample's depth plus detector
  noise), and a limb's score is ``conf_a * conf_b``: both endpoints come from
  one detection, which is the association the part affinity field provides.
- **confidence maps + part affinity fields** (bottom-up models, eq. 5.8 as
  written): :func:`heatmap_joint_scores` and :func:`paf_limb_scores` sample the
  maps at the projected joints / along the projected limbs.

Eq. 5.7 is evaluated in log space with the epsilon added per limb, so a limb
that no camera of the pair sees contributes the same factor to every sample:
``log Phi(v, s) = sum_l log(sqrt(sum_{c in v} phi(c,l,s)^2) + eps)``.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment

from roomcap.track import kernels
from roomcap.track.priors import normal_noise


def camera_pairs(n_cams: int) -> np.ndarray:
    """All camera pairs (V,2); a single camera is its own 'pair' (1,2) = [[0,0]]."""
    if n_cams < 1:
        raise ValueError("need at least one camera")
    if n_cams == 1:
        return np.zeros((1, 2), np.int64)
    return np.asarray(list(itertools.combinations(range(n_cams), 2)), np.int64)


def project(P: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pinhole projection on undistorted pixels. P: (C,3,4); X: (...,3) -> uv (C,...,2), depth (C,...)."""
    P = np.asarray(P, np.float32)
    X = np.asarray(X, np.float32)
    h = np.tensordot(X, P[:, :, :3], axes=([-1], [2]))  # (...,C,3)
    h = np.moveaxis(h, -2, 0) + P[:, :, 3].reshape((len(P),) + (1,) * (X.ndim - 1) + (3,))
    z = h[..., 2]
    zs = np.where(z > 1e-3, z, np.float32(1e-3))
    return h[..., :2] / zs[..., None], z


def camera_rays(P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Camera centres (C,3) and the matrices (C,3,3) that turn undistorted pixels [u,v,1] into ray
    directions."""
    P = np.asarray(P, np.float64)
    M = P[:, :, :3]
    Minv = np.linalg.inv(M)
    centers = -np.einsum("cab,cb->ca", Minv, P[:, :, 3])
    return centers.astype(np.float32), Minv.astype(np.float32)


def ray_basis(Minv: np.ndarray, kp: np.ndarray) -> np.ndarray:
    """Orthonormal frames of the keypoints' viewing rays. Minv: (C,3,3); kp: (K,C,J,2) undistorted px.

    Returns B (K,J,3C,3): rows [u_0..u_{C-1}, w_0..w_{C-1}, r_0..r_{C-1}] with r_c the unit ray of the
    keypoint in camera c and u_c, w_c spanning the plane perpendicular to it (NaN keypoints give any frame;
    their score is 0).
    """
    h = np.concatenate([np.nan_to_num(kp), np.ones(kp.shape[:-1] + (1,), np.float32)], -1)
    r = np.einsum("cab,kcjb->kjca", Minv, h)
    r /= np.linalg.norm(r, axis=-1, keepdims=True)
    helper = np.where(np.abs(r[..., 2:3]) < 0.9, np.float32([0, 0, 1]), np.float32([1, 0, 0]))
    u = np.cross(r, helper)
    u /= np.linalg.norm(u, axis=-1, keepdims=True)
    w = np.cross(r, u)
    return np.concatenate([u, w, r], 2).astype(np.float32)


def ray_coords(X: np.ndarray, centers: np.ndarray, basis: np.ndarray) -> np.ndarray:
    """Coordinates of sample joints in the ray frames. X: (K,N,J,3), centers (C,3), basis (K,J,3C,3) ->
    Y (K,J,3C,N): rows :2C are the offsets from the rays (metres), rows 2C: the depth along them."""
    xt = np.ascontiguousarray(X.transpose(0, 2, 3, 1))  # (K,J,3,N)
    off = (basis * np.tile(centers, (3, 1))[None, None]).sum(-1)  # (K,J,3C): rows repeat the C centres
    Y = np.matmul(basis, xt)
    Y -= off[..., None]  # in place: no second (K,J,3C,N) array
    return Y


def _variance(along: np.ndarray, focal_px: np.ndarray, sigma_m: float, sigma_px: float) -> np.ndarray:
    """Tolerance s^2 = sigma_m^2 + (sigma_px * depth / f)^2. along: (K,J,C,N...) depths."""
    f = np.asarray(focal_px, np.float32).reshape((1, 1, -1) + (1,) * (along.ndim - 3))
    return np.float32(sigma_m**2) + (np.float32(sigma_px) * along / f) ** 2


def _kernel(q: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """Peak shape of a keypoint's 'confidence map' for squared normalised distance q = d^2 / s^2:
    ``1 / (1 + q / 2)`` (Cauchy). Equal to the Gaussian's curvature at the peak, but with heavy tails, so a
    sample that fell off a fast-moving joint still feels the detection (a Gaussian gives it nothing)."""
    q = np.multiply(q, np.float32(0.5), out=out)
    q += np.float32(1.0)
    return np.reciprocal(q, out=q)


def joint_scores(
    X: np.ndarray,
    centers: np.ndarray,
    basis: np.ndarray,
    sc: np.ndarray,
    focal_px: np.ndarray,
    sigma_m: float,
    sigma_px: float,
    Y: np.ndarray | None = None,
) -> np.ndarray:
    """Keypoint 'confidence map' value of every sample joint in every camera.

    X: (K,N,J,3) samples; centers: (C,3); basis: (K,J,3C,3) from :func:`ray_basis` for each track's
    associated keypoints; sc: (K,C,J) their scores (0 = none); focal_px: (C,); Y: the samples' ray
    coordinates if already computed (:func:`ray_coords`). Returns conf (K,C,J,N) in [0, 1]:
    ``sc * k(d^2 / s^2)`` (:func:`_kernel`) with d the distance of the joint from the keypoint's viewing
    ray (the image distance seen at the joint's depth) and ``s^2 = sigma_m^2 + (sigma_px * depth / f)^2``.
    """
    C = len(centers)
    if Y is None:
        Y = ray_coords(X, centers, basis)
    along = Y[:, :, 2 * C :]
    d2 = Y[:, :, :C] ** 2 + Y[:, :, C : 2 * C] ** 2  # (K,J,C,N)
    conf = _kernel(d2 / _variance(along, focal_px, sigma_m, sigma_px))
    conf *= np.where(along > 0.05, sc.transpose(0, 2, 1)[..., None], np.float32(0.0))
    return conf.transpose(0, 2, 1, 3)


def limb_scores(conf: np.ndarray, limbs: np.ndarray, axis: int = -1) -> np.ndarray:
    """phi(c, l, s) from joint confidences (keypoint evidence): conf_a * conf_b along the joint ``axis``
    (J -> L); e.g. (K,C,J,N) with axis=2 -> (K,C,L,N)."""
    return np.take(conf, limbs[:, 0], axis) * np.take(conf, limbs[:, 1], axis)


def log_phi_pairs(phi: np.ndarray, pairs: np.ndarray, eps: float) -> np.ndarray:
    """Eq. 5.7 in log space per camera pair. phi: (K,C,L,N) -> log Phi (K,V,N).

    With ``pairs`` = :func:`camera_pairs` (C), the pairs (a, b > a) in order, the pairs of one first camera a
    are one broadcast ``p2[a] + p2[a+1:]`` (no gather of a (K,V,L,N) array: 2.7x faster at 12 cameras); any
    other pair list takes the gather. Both give the same bits."""
    K, C, L, N = phi.shape
    p2 = phi * phi
    # sum of logs = log of products over groups of g limbs (each factor >= eps: eps^g stays above float32's
    # smallest normal 1e-38; one log per group instead of per limb)
    g = int(max(1, min(8, 35 // max(1.0, -np.log10(eps)))))
    if C == 1 or not np.array_equal(pairs, camera_pairs(C)):
        return _log_phi_pairs_gather(p2, pairs, eps, g)
    out = np.empty((K, len(pairs), N), np.float32)
    v0 = 0
    for a in range(C - 1):  # loop over the first camera of the pairs only
        nb = C - a - 1
        s = p2[:, a : a + 1] + p2[:, a + 1 :]  # (K,nb,L,N)
        np.sqrt(s, out=s)
        s += np.float32(eps)
        acc = np.log(s[:, :, :g].prod(2))
        for l0 in range(g, L, g):  # loop over limb groups only
            acc += np.log(s[:, :, l0 : l0 + g].prod(2))
        out[:, v0 : v0 + nb] = acc
        v0 += nb
    return out


def _log_phi_pairs_gather(p2: np.ndarray, pairs: np.ndarray, eps: float, g: int) -> np.ndarray:
    """:func:`log_phi_pairs` for any list of pairs (a pair (c, c) = camera c alone)."""
    distinct = pairs[:, 0] != pairs[:, 1]
    s = p2[:, pairs[:, 0]]
    if distinct.all():
        s += p2[:, pairs[:, 1]]
    else:
        s += distinct.astype(np.float32)[None, :, None, None] * p2[:, pairs[:, 1]]
    np.sqrt(s, out=s)
    s += np.float32(eps)
    L = s.shape[2]
    out = np.zeros(s.shape[:2] + s.shape[3:], np.float32)
    for l0 in range(0, L, g):  # loop over limb groups only
        out += np.log(s[:, :, l0 : l0 + g].prod(2))
    return out


def log_phi_all(phi: np.ndarray, eps: float) -> np.ndarray:
    """Eq. 5.7 with v = all cameras (initial scoring and inference, sec. 5.2.3–5.2.4). (K,C,L,N) -> (K,N)."""
    return np.log(np.sqrt((phi**2).sum(1)) + np.float32(eps)).sum(1)


def normalized_weights(log_phi: np.ndarray) -> np.ndarray:
    """Eq. 5.6: normalise over samples (last axis)."""
    w = np.exp(log_phi - log_phi.max(-1, keepdims=True))
    return w / w.sum(-1, keepdims=True)


def pair_sizes(n_samples: int, n_pairs: int) -> np.ndarray:
    """How many samples each camera pair draws, summing to n_samples."""
    base = np.full(n_pairs, n_samples // n_pairs)
    base[: n_samples - base.sum()] += 1
    return base


def stochastic_universal_indices(w: np.ndarray, counts: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Stochastic universal sampling for all rows at once.

    w: (R,N) normalised weights per row (track x camera pair), counts: (R,) samples to draw per row.
    Returns flat indices into N of length counts.sum(), grouped by row in order.
    """
    R, N = w.shape
    cdf = np.cumsum(w, -1)
    cdf /= cdf[:, -1:]
    cdf[:, -1] = 1.0
    rows = np.repeat(np.arange(R), counts)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    within = np.arange(counts.sum()) - np.repeat(starts, counts)
    u = rng.random(R)
    pos = (u[rows] + within) / np.maximum(counts[rows], 1)
    flat = (cdf + np.arange(R)[:, None] * 2.0).ravel()  # rows separated by offsets of 2
    idx = np.searchsorted(flat, pos + rows * 2.0, side="left") - rows * N
    return np.clip(idx, 0, N - 1)


def resample_pairs(log_phi_v: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Per-camera-pair resampling (fig. 5.2). log_phi_v: (K,V,N) -> indices (K,N) into each track's
    samples."""
    K, V, N = log_phi_v.shape
    w = normalized_weights(log_phi_v).reshape(K * V, N)
    counts = np.tile(pair_sizes(N, V), K)
    return stochastic_universal_indices(w, counts, rng).reshape(K, N)


def refine_scales(n_candidates: int, sigma_m: float) -> np.ndarray:
    """Spread of each refinement candidate (M,): 0 for the current position, then
    sigma_m * (1/2, 1, 2, 4, ...) cycling, so the search covers small corrections and fast motion alike."""
    cyc = np.float32([0.5, 1.0, 2.0, 4.0])
    s = np.zeros(n_candidates, np.float32)
    s[1:] = cyc[np.arange(n_candidates - 1) % len(cyc)] * np.float32(sigma_m)
    return s


def guided_targets(
    X: np.ndarray, centers: np.ndarray, basis: np.ndarray, sc: np.ndarray, lam: float = 0.01
) -> np.ndarray:
    """Where the evidence puts each sample joint: argmin_x' sum_c s_c |x' - ray_c|^2 + lam |x' - x|^2.

    With two or more views this is the joint triangulated from the track's detections; with one view it is
    the sample's joint moved onto the viewing ray at its own depth; with none it stays. Closed form per
    track and joint, one batched 3x3 product for all samples. X: (K,N,J,3) -> (K,J,3,N).
    """
    K, N, J, _ = X.shape
    C = len(centers)
    r = basis[:, :, 2 * C :]  # (K,J,C,3)
    s = sc.transpose(0, 2, 1)[..., None, None]  # (K,J,C,1,1)
    Q = np.eye(3, dtype=np.float32) - r[..., :, None] * r[..., None, :]  # (K,J,C,3,3)
    A = (s * Q).sum(2) + np.float32(lam) * np.eye(3, dtype=np.float32)
    b = (s[..., 0] * np.einsum("kjcab,cb->kjca", Q, centers)).sum(2)  # (K,J,3)
    Ainv = np.linalg.inv(A)
    xt = np.ascontiguousarray(X.transpose(0, 2, 3, 1))  # (K,J,3,N)
    return np.matmul(Ainv, b[..., None] + np.float32(lam) * xt)


def _candidate_offsets(
    X, centers, basis, sc, M: int, sigma_refine_m: float, n_guided: int, rng
) -> np.ndarray:
    """The M-1 candidate offsets of every joint of every sample, (K,J,3,R,N) with the samples innermost (so
    every broadcast of the refinement runs over contiguous N): random at the refinement's scales, the
    last ``n_guided`` of them a quarter as wide around :func:`guided_targets`."""
    K, N, J, _ = X.shape
    R = M - 1
    e = normal_noise(rng, (K, J, 3, R, N), 1.0)
    e *= refine_scales(M, sigma_refine_m)[1:, None]
    G = min(n_guided, R)
    if G > 0:
        e[:, :, :, R - G :] *= np.float32(
            0.25
        )  # 1/2, 1/4, 1/8, 1/16 of the random scales: sigma/4 on average
        xt = X.transpose(0, 2, 3, 1)
        e[:, :, :, R - G :] += (guided_targets(X, centers, basis, sc) - xt)[:, :, :, None]
    return e


def refine_joints(
    X: np.ndarray,
    centers: np.ndarray,
    basis: np.ndarray,
    sc: np.ndarray,
    focal_px: np.ndarray,
    sigma_m: float,
    sigma_px: float,
    n_candidates: int,
    sigma_refine_m: float,
    rng: np.random.Generator,
    n_guided: int = 0,
    Y: np.ndarray | None = None,
) -> np.ndarray:
    """Joint refinement (sec. 5.2.2): per joint of every sample, draw M-1 positions around it and keep the one
    with the highest confidence summed over cameras (the current position, candidate 0, wins ties).

    With ``n_guided`` > 0, that many of the M candidates are drawn around :func:`guided_targets` (spread
    sigma_refine_m / 2) instead of around the current position: a data-driven proposal that keeps up with
    fast joints in one frame (our addition; the argmax over candidates is unchanged).

    X: (K,N,J,3) -> refined X (K,N,J,3) and the kept candidates' confidence summed over cameras (K,J,N);
    other arguments as :func:`joint_scores`. Candidates are scored in the
    keypoints' ray frames: one batched product ``basis @ offsets`` per frame, no loop; the tolerance uses
    the mean depth of the samples per track, joint and camera.
    """
    K, N, J, _ = X.shape
    M = int(n_candidates)
    if M <= 1 or K == 0:
        raise ValueError(f"refine_joints needs at least 2 candidates and one track, got M={M}, K={K}")
    C = len(centers)
    e = _candidate_offsets(X, centers, basis, sc, M, sigma_refine_m, int(n_guided), rng)
    if Y is None:
        Y = ray_coords(X, centers, basis)  # (K,J,3C,N)
    along = Y[:, :, 2 * C :].mean(-1, keepdims=True)  # (K,J,C,1): one tolerance per track, joint, camera
    scale = np.sqrt(0.5 / _variance(along, focal_px, sigma_m, sigma_px))  # folds 1/(2 s^2) into the frame
    scale2 = np.concatenate([scale, scale], 2)  # (K,J,2C,1)
    s = np.where(along > 0.05, sc.transpose(0, 2, 1)[..., None], np.float32(0.0))  # (K,J,C,1)
    Bs = basis[:, :, : 2 * C] * scale2
    return _best_candidates(X, e, Y, Bs, s, scale2)


def _best_candidates(X, e, Y, Bs, s, scale2) -> tuple[np.ndarray, np.ndarray]:
    """Each joint of each sample moved to its best candidate (the current position wins ties), scored in
    the keypoints' ray frames (``Bs``: the frames' rows scaled by 1 / (2 s^2)); returns X' and the kept
    candidates' confidence summed over cameras (K,J,N)."""
    K, N, J, _ = X.shape
    R, C = e.shape[3], s.shape[2]
    # all tracks and joints in one batch (KJ rows); chunks of rows keep the candidates in cache
    KJ = K * J
    e2 = e.reshape(KJ, 3, R * N)
    Bs, s = Bs.reshape(KJ, 2 * C, 3), s.reshape(KJ, C, 1, 1)
    Y2, scale2 = Y.reshape(KJ, 3 * C, N), scale2.reshape(KJ, 2 * C, 1)
    score = np.empty((K, J, N), np.float32)  # the current positions' confidence summed over cameras
    sc0 = score.reshape(KJ, N)
    delta = np.empty((KJ, 3, N), np.float32)
    rb = max(1, 16384 // (N * R))
    for r0 in range(0, KJ, rb):  # loop over row chunks only
        r1 = min(KJ, r0 + rb)
        Ys = Y2[r0:r1, : 2 * C] * scale2[r0:r1]  # (rows,2C,N)
        q0 = Ys * Ys
        q0 = q0[:, :C] + q0[:, C:]
        q0 += np.float32(1.0)
        np.divide(s[r0:r1, :, 0], q0, out=q0)
        q0.sum(1, out=sc0[r0:r1])
        D = np.matmul(Bs[r0:r1], e2[r0:r1]).reshape(r1 - r0, 2 * C, R, N)
        D += Ys[:, :, None]
        D *= D
        q = D[:, :C]
        q += D[:, C:]  # q = d^2 / (2 s^2) per camera, (rows,C,R,N)
        q += np.float32(1.0)
        np.divide(s[r0:r1], q, out=q)  # s / (1 + d^2 / 2 s^2): the kernel of joint_scores
        tot = q.sum(1)  # (rows,R,N)
        ek = e2[r0:r1].reshape(r1 - r0, 3, R, N)
        if R == 1:
            tbest, e_best = tot[:, 0], ek[:, :, 0]
        elif R == 2:
            pick = tot[:, 1] > tot[:, 0]
            tbest = np.maximum(tot[:, 0], tot[:, 1])
            e_best = np.where(pick[:, None], ek[:, :, 1], ek[:, :, 0])
        else:
            best = tot.argmax(1)  # (rows,N)
            tbest = np.take_along_axis(tot, best[:, None], 1)[:, 0]
            e_best = np.take_along_axis(ek, best[:, None, None], 2)[:, :, 0]
        better = tbest > sc0[r0:r1]  # the current position wins ties
        np.maximum(tbest, sc0[r0:r1], out=sc0[r0:r1])
        np.multiply(e_best, better[:, None, :], out=delta[r0:r1])
    out = X + delta.reshape(K, J, 3, N).transpose(0, 3, 1, 2)
    return out, score


def weighted_stats(X: np.ndarray, log_phi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sec. 5.2.4: weighted mean pose and per-joint spread. X: (K,N,J,3), log_phi: (K,N) ->
    mean (K,J,3), std_m (K,J) = sqrt(weighted mean squared distance to the mean / 3) (per-axis RMS)."""
    w = normalized_weights(log_phi)
    mean = np.einsum("kn,knja->kja", w, X)
    d2 = ((X - mean[:, None]) ** 2).sum(-1)
    std = np.sqrt(np.einsum("kn,knj->kj", w, d2) / 3.0)
    return mean, std


def nanmedian_last(x: np.ndarray) -> np.ndarray:
    """``np.nanmedian(x, -1)`` (the same values: the mean of the two middle ones for an even count; NaN for
    a row without any finite value) by one sort of all rows: 7x faster on the small rows of
    :func:`associate`, where nanmedian loops in Python."""
    s = np.sort(x, -1)  # NaN sort last
    m = (~np.isnan(s)).sum(-1)
    lo = np.take_along_axis(s, np.maximum((m - 1) // 2, 0)[..., None], -1)[..., 0]
    hi = np.take_along_axis(s, np.maximum(m // 2 - (m == 0), 0)[..., None], -1)[..., 0]
    return np.where(m > 0, (lo + hi) / 2, np.nan)


def association_costs(
    mean_uv: np.ndarray,
    mean_depth: np.ndarray,
    det_kp: np.ndarray,
    det_sc: np.ndarray,
    *,
    focal_px: np.ndarray,
    tol_m: float,
    min_joints: int,
    min_score: float,
) -> np.ndarray:
    """The cost of :func:`associate` for every track-detection pair (C,K,D): the median joint distance in
    units of ``tol_m`` seen at the joint's depth, on the joints both have; inf with fewer than
    ``min_joints``. :func:`associate` computes it with :func:`roomcap.track.kernels.association_costs` (inf
    where it reaches the gate); this is the numpy reference."""
    ok_det = np.isfinite(det_kp).all(-1) & (det_sc >= min_score)  # (C,D,J)
    d = np.linalg.norm(mean_uv[:, :, None] - det_kp[:, None], axis=-1)  # (C,K,D,J)
    scale = (
        np.asarray(focal_px, np.float64)[:, None, None, None]
        * tol_m
        / np.maximum(mean_depth[:, :, None], 0.1)
    )
    r = d / scale
    both = ok_det[:, None] & np.isfinite(r) & (mean_depth[:, :, None] > 0.1)
    r = np.where(both, r, np.nan)
    n = both.sum(-1)
    cost = nanmedian_last(np.where(n[..., None] > 0, r, 0.0))
    return np.where(n >= min_joints, cost, np.inf)


def associate(
    mean_uv: np.ndarray,
    mean_depth: np.ndarray,
    det_kp: np.ndarray,
    det_sc: np.ndarray,
    focal_px: np.ndarray,
    tol_m: float,
    gate: float | np.ndarray,
    min_joints: int,
    min_score: float,
) -> np.ndarray:
    """One detection per track and camera (Hungarian on the predicted mean pose).

    mean_uv: (C,K,J,2), mean_depth: (C,K,J) projections of the tracks' predicted means;
    det_kp: (C,D,J,2), det_sc: (C,D,J). The cost is the median joint distance in units of
    ``tol_m`` seen at the joint's depth (:func:`association_costs`); ``gate``: a number or one per track
    (K,). Returns assignment (C,K): detection index or -1.
    """
    C, K = mean_uv.shape[:2]
    D = det_kp.shape[1]
    out = np.full((C, K), -1, np.int64)
    if K == 0 or D == 0:
        return out
    gate_k = np.ascontiguousarray(np.broadcast_to(np.asarray(gate, np.float64), (K,)))
    cost = kernels.association_costs(
        np.ascontiguousarray(mean_uv, np.float32),
        np.ascontiguousarray(mean_depth, np.float32),
        np.ascontiguousarray(det_kp, np.float32),
        np.ascontiguousarray(det_sc, np.float32),
        focal=np.ascontiguousarray(focal_px, np.float32),
        tol_m=float(tol_m),
        min_joints=int(min_joints),
        min_score=float(min_score),
        gate=gate_k,
    )  # inf where the cost reaches the gate
    gate_k = gate_k[:, None]
    for c in range(C):  # Hungarian per camera; C is small
        cc = cost[c]
        big = np.where(np.isfinite(cc) & (cc < gate_k), cc, 1e6)
        rows, cols = linear_sum_assignment(big)
        keep = big[rows, cols] < 1e6
        out[c, rows[keep]] = cols[keep]
    return out


# --- confidence maps and part affinity fields (eq. 5.8 as written) ---------------------------------------


def _sample_map(maps: np.ndarray, uv_map: np.ndarray) -> np.ndarray:
    """Bilinear lookup. maps: (Q,H,W) or (Q,G,H,W) (G channels per map, e.g. PAF x/y); uv_map: (...,Q,2) in
    map pixels -> (...,Q) or (...,Q,G); 0 outside. One flat gather per corner for all points."""
    maps = np.asarray(maps, np.float32)
    Q, H, W = maps.shape[0], maps.shape[-2], maps.shape[-1]
    G = 1 if maps.ndim == 3 else maps.shape[1]
    u, v = uv_map[..., 0], uv_map[..., 1]
    with np.errstate(invalid="ignore"):
        inside = (u >= 0) & (v >= 0) & (u <= W - 1) & (v <= H - 1)
    u = np.clip(np.nan_to_num(u, nan=-1.0), 0, W - 1.001).astype(np.float32)
    v = np.clip(np.nan_to_num(v, nan=-1.0), 0, H - 1.001).astype(np.float32)
    u0, v0 = np.floor(u), np.floor(v)
    fu, fv = u - u0, v - v0
    base = (np.arange(Q, dtype=np.int64) * (G * H * W))[None] + (
        v0.astype(np.int64) * W + u0.astype(np.int64)
    )
    flat = maps.reshape(-1)
    w00, w01, w10, w11 = (1 - fu) * (1 - fv), fu * (1 - fv), (1 - fu) * fv, fu * fv
    outs = []
    for g in range(G):  # loop over channels per map (1 or 2) only
        b = base + g * H * W
        val = flat[b] * w00 + flat[b + 1] * w01 + flat[b + W] * w10 + flat[b + W + 1] * w11
        outs.append(np.where(inside, val, np.float32(0.0)))
    return outs[0] if maps.ndim == 3 else np.stack(outs, -1)


def heatmap_joint_scores(uv_px: np.ndarray, heatmaps: np.ndarray, px_to_map: float) -> np.ndarray:
    """conf_c(s, j) of eq. 5.8 for one camera. uv_px: (...,J,2) image px; heatmaps: (J,H,W) -> (...,J)."""
    return _sample_map(np.asarray(heatmaps, np.float32), np.asarray(uv_px, np.float32) * px_to_map)


def paf_limb_scores(
    uv_px: np.ndarray, pafs: np.ndarray, paf_limbs: np.ndarray, px_to_map: float, n_steps: int = 5
) -> np.ndarray:
    """Integral term of eq. 5.8 for one camera: mean over u of max(0, <paf(l, p(u)), unit(limb)>).

    uv_px: (...,J,2); pafs: (L,2,H,W) (x and y components); paf_limbs: (L,2) joint index pairs -> (...,L).
    """
    a = uv_px[..., paf_limbs[:, 0], :] * px_to_map
    b = uv_px[..., paf_limbs[:, 1], :] * px_to_map
    d = b - a
    unit = d / np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), 1e-6)
    steps = np.linspace(0.0, 1.0, n_steps, dtype=np.float32).reshape((n_steps,) + (1,) * a.ndim)
    f = _sample_map(pafs, a[None] + steps * d[None])  # (S,...,L,2): all integration steps at once
    dot = (f * unit[None]).sum(-1)
    return np.maximum(dot, np.float32(0.0)).mean(0)


def heatmap_limb_scores(
    uv_px: np.ndarray,
    heatmaps: np.ndarray,
    pafs: np.ndarray,
    limbs: np.ndarray,
    paf_limbs: np.ndarray,
    px_to_map: float,
) -> np.ndarray:
    """Eq. 5.8 for one camera: phi(c,l,s) = PAF integral * conf(a) * conf(b). uv_px: (...,J,2) -> (...,L).

    ``limbs`` (L,2) are the scored limbs; ``paf_limbs`` (L,2) the same limbs in the model's PAF order
    (row l of both must describe the same limb).
    """
    conf = heatmap_joint_scores(uv_px, heatmaps, px_to_map)
    return paf_limb_scores(uv_px, pafs, paf_limbs, px_to_map) * limb_scores(conf, limbs)


# --- the filter's maps path: one camera's maps for one frame, scored for all samples at once -------------


def paf_limbs_in(skeleton, map_joint_names, paf_limbs) -> np.ndarray:
    """The PAF limbs (L,2) of a map model (indices into ``map_joint_names``) as joint indices of
    ``skeleton``; a limb whose joint the skeleton lacks raises (every coco18 joint is in body19)."""
    names = list(skeleton.joint_names)
    try:
        return np.asarray(
            [[names.index(map_joint_names[a]), names.index(map_joint_names[b])] for a, b in paf_limbs],
            np.int64,
        )
    except ValueError as e:
        raise ValueError(
            f"the map model's joints {list(map_joint_names)} are not all in skeleton '{skeleton.id}' ({e})"
        ) from None


@dataclass(frozen=True)
class CameraMaps:
    """A bottom-up model's output for one camera and frame (eq. 5.8 as written).

    heat: (J,H,W) confidence maps already in the tracker skeleton's joint order (zeros for joints the
    model lacks, e.g. body19's pelvis); paf: (L,2,H,W) x/y fields of the limbs ``limbs`` (L,2) (tracker
    joint indices, same row order); img_to_map: (2,3) affine from image px to map px;
    distort: optional function undistorted px (...,2) -> image px (...,2) (the maps are in image px,
    the filter projects on undistorted px); None = no distortion.
    """

    heat: np.ndarray
    paf: np.ndarray
    limbs: np.ndarray
    img_to_map: np.ndarray
    distort: object = None

    def __post_init__(self) -> None:
        if self.heat.ndim != 3 or self.paf.ndim != 4 or self.paf.shape[1] != 2:
            raise ValueError(
                f"heat must be (J,H,W) and paf (L,2,H,W), got {self.heat.shape}, {self.paf.shape}"
            )
        if self.paf.shape[2:] != self.heat.shape[1:] or len(self.limbs) != len(self.paf):
            raise ValueError(
                f"paf {self.paf.shape} does not fit heat {self.heat.shape} / limbs {np.shape(self.limbs)}"
            )


def map_limb_scores(X: np.ndarray, P: np.ndarray, maps: CameraMaps, n_steps: int = 5) -> np.ndarray:
    """phi(c,l,s) of eq. 5.8 from one camera's maps for all samples at once: the PAF line integral along the
    projected limb times the confidence maps at its projected ends. X: (K,N,J,3); P: (3,4) on undistorted
    px -> (K,L,N) with L = len(maps.limbs). Samples behind the camera score 0."""
    K, N, J, _ = X.shape
    uv, z = project(np.asarray(P, np.float32)[None], X.reshape(K * N, J, 3))
    uv, z = uv[0], z[0]  # (K*N,J,2), (K*N,J)
    if maps.distort is not None:
        uv = np.asarray(maps.distort(uv), np.float32)
    A = np.asarray(maps.img_to_map, np.float32)
    uvm = uv @ A[:, :2].T + A[:, 2]
    uvm = np.where((z > 0.05)[..., None], uvm, np.float32(-1e6))  # behind the camera: outside the map
    conf = heatmap_joint_scores(uvm, maps.heat, 1.0)  # (K*N,J)
    phi = paf_limb_scores(uvm, maps.paf, maps.limbs, 1.0, n_steps) * limb_scores(conf, maps.limbs)
    return np.ascontiguousarray(phi.reshape(K, N, -1).transpose(0, 2, 1)).astype(np.float32)
