"""Compiled kernels of the particle filter's hot loops (numba; seed ch. 5.2.1–5.2.4).

Each kernel fuses a chain of numpy passes over (K,J,C,N) arrays that :mod:`roomcap.track.observation` and
:mod:`roomcap.track.motion` write as whole-array expressions; the numpy functions stay the reference
(``tests/test_track_kernels.py`` checks that both agree). Shapes: K tracks, N samples, J joints, L limbs,
C cameras, V camera pairs, D detections, B = K·N.

- :func:`pair_weights`: ray coordinates, keypoint confidences, limb scores and eq. 5.7 per camera pair
  in one pass per block of samples (observation's ``ray_coords``, ``joint_scores``, ``limb_scores``,
  ``log_phi_pairs``), returned as Phi(v, s) itself, not its log: eq. 5.6 needs only ratios of Phi
  within a row.
- :func:`sus_indices`: eq. 5.6's normalisation and stochastic universal resampling per camera pair
  (observation's ``resample_pairs``), the uniform draws given.
- :func:`refine_resampled`: the gather of the resampled samples and the joint refinement of sec. 5.2.2
  with the guided candidates (observation's ``refine_joints``, ``guided_targets``).
- :func:`output_stats`: the output weights (product over joints of the refined scores) and sec. 5.2.4's
  weighted mean and spread (observation's ``weighted_stats``).
- :func:`ray_basis`, :func:`association_costs`: the keypoints' ray frames and the association's cost
  table (the same bits as observation's).
- :func:`gather_state`: the resampling's gather of the motion state; the GRU prior's own kernels are
  :mod:`roomcap.track.kernels_gru`.

Arithmetic is float32 where the numpy path's is, with float64 products and sums where a range or an
accumulation needs it; the results agree with numpy to float32 rounding, not bit for bit (fused
expressions, other summation orders). ``fastmath`` is off (IEEE arithmetic, no reassociation);
``error_model="numpy"`` lets a division by zero give inf as in numpy instead of raising, which is what
lets the loops vectorise. The kernels index without bounds checks, so each checks its shapes and index
arrays first (ValueError). They compile on first use (about 15 s for all on a loaded 2-core machine)
and are cached on disk (``cache=True``): a later process loads them in ~0.3 s. The cache is numba's:
next to this file (``track/__pycache__``), else, in an install that cannot be written, the user's cache
folder (``~/.cache/numba``); where neither can be written, a folder in the temp directory
(:func:`_cache_fallback`) rather than numba's error at import. ``NUMBA_CACHE_DIR`` overrides all three.
"""

from __future__ import annotations

import math
import os
import tempfile
from pathlib import Path

import numba
import numpy as np
from numba import njit
from numba.misc.appdirs import AppDirs


def _writable(folder: Path) -> bool:
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=folder):
            return True
    except OSError:
        return False


def _cache_fallback() -> None:
    """Point numba's cache at the temp directory when neither this package's ``__pycache__`` nor the user's
    cache folder can be written (numba raises at decoration time then: "no locator available")."""
    if numba.config.CACHE_DIR:
        return
    user = Path(AppDirs(appname="numba", appauthor=False).user_cache_dir)
    if _writable(Path(__file__).parent / "__pycache__") or _writable(user):
        return
    numba.config.CACHE_DIR = str(Path(tempfile.gettempdir()) / f"roomcap-numba-{os.getuid()}")


_cache_fallback()

_F = np.float32
_NB = 128  # samples per block of pair_weights: (C,J,NB) + (C,L,NB) float32 scratch stay in L2


@njit(cache=True, nogil=True, error_model="numpy")
def _in_range(a, n):
    """Every entry of the integer array ``a`` lies in [0, n) (the kernels index without bounds checks)."""
    f = a.ravel()
    for i in range(f.shape[0]):
        if f[i] < 0 or f[i] >= n:
            return False
    return True


@njit(cache=True, nogil=True, error_model="numpy")
def _check_scores(basis, sc, focal, K, J, C):
    """The shapes the scoring kernels index without bounds checks: basis (K,J,3C,3), sc (K,C,J),
    focal (C,)."""
    if basis.shape != (K, J, 3 * C, 3) or sc.shape != (K, C, J) or focal.shape[0] != C:
        raise ValueError("basis must be (K,J,3C,3), sc (K,C,J) and focal (C,)")


@njit(cache=True, nogil=True, error_model="numpy")
def _ray_rows(basis, centers, k, j, c, C):
    """Rows u, w, r of camera c's ray frame for track k, joint j, and their offsets (rows · centre)."""
    u0, u1, u2 = basis[k, j, c, 0], basis[k, j, c, 1], basis[k, j, c, 2]
    w0, w1, w2 = basis[k, j, C + c, 0], basis[k, j, C + c, 1], basis[k, j, C + c, 2]
    r0, r1, r2 = basis[k, j, 2 * C + c, 0], basis[k, j, 2 * C + c, 1], basis[k, j, 2 * C + c, 2]
    cx, cy, cz = centers[c, 0], centers[c, 1], centers[c, 2]
    ou = u0 * cx + u1 * cy + u2 * cz
    ow = w0 * cx + w1 * cy + w2 * cz
    orr = r0 * cx + r1 * cy + r2 * cz
    return u0, u1, u2, w0, w1, w2, r0, r1, r2, ou, ow, orr


@njit(cache=True, nogil=True, error_model="numpy")
def _pair_rows(pairs, active, C):
    """For each camera pair (V,2) the first pair whose Phi row equals its own, and each camera's slot in
    the squared limb scores: a camera without evidence for the track (``active`` False: every score 0)
    scores 0 everywhere, exactly as the zero row C a camera alone is paired with, so a pair with such a
    camera gives the same bits as the other camera alone, and a pair of two such cameras eps^L."""
    V = pairs.shape[0]
    first = np.empty((C + 1, C + 1), np.int64)
    for a in range(C + 1):
        for b in range(C + 1):
            first[a, b] = -1
    rep = np.empty(V, np.int64)
    slot = np.empty((V, 2), np.int64)
    for v in range(V):
        a, b = pairs[v, 0], pairs[v, 1]
        a = a if active[a] else C
        b = b if active[b] and b != pairs[v, 0] else C
        lo, hi = min(a, b), max(a, b)  # sqrt(p2[a] + p2[b]): the sum is the same bits either way round
        if first[lo, hi] < 0:
            first[lo, hi] = v
        rep[v] = first[lo, hi]
        slot[v, 0], slot[v, 1] = lo, hi
    return rep, slot


@njit(cache=True, error_model="numpy", inline="always")
def _camera_conf(basis, centers, sc, focal, k, c, C, xt, nb, sm2, spx, conf):
    """Into ``conf[c]`` (J,nb): camera ``c``'s keypoint evidence of track ``k``'s samples ``xt`` (J,3,nb):
    conf = sc k(d^2 / s^2) (:func:`roomcap.track.observation.joint_scores`), 0 where the camera has no
    keypoint."""
    J = xt.shape[0]
    near = _F(0.05)
    g = spx / _F(focal[c])
    for j in range(J):
        s = sc[k, c, j]
        if s == 0:
            for i in range(nb):
                conf[c, j, i] = 0
            continue
        u0, u1, u2, w0, w1, w2, r0, r1, r2, ou, ow, orr = _ray_rows(basis, centers, k, j, c, C)
        for i in range(nb):
            x0, x1, x2 = xt[j, 0, i], xt[j, 1, i], xt[j, 2, i]
            yu = u0 * x0 + u1 * x1 + u2 * x2 - ou  # offsets from the ray (m)
            yw = w0 * x0 + w1 * x1 + w2 * x2 - ow
            d = r0 * x0 + r1 * x1 + r2 * x2 - orr  # depth along it
            gd = g * d
            v2 = _F(2.0) * (sm2 + gd * gd)  # 2 s^2
            kv = v2 / (v2 + (yu * yu + yw * yw))  # 1 / (1 + d^2 / 2 s^2): observation._kernel
            conf[c, j, i] = kv * s if d > near else _F(0.0)


@njit(cache=True, nogil=True, error_model="numpy")
def pair_weights(X, centers, basis, sc, *, focal, sigma_m, sigma_px, eps, limbs, pairs):
    """Phi(v, s) of eq. 5.7 for every track, camera pair and sample. X: (K,N,J,3) float32; centers: (C,3);
    basis: (K,J,3C,3) (:func:`roomcap.track.observation.ray_basis`); sc: (K,C,J) associated keypoint scores
    (0 = none); focal: (C,); limbs: (L,2); pairs: (V,2) (a pair (c, c) = camera c alone). Returns (K,V,N)
    float64: prod_l (sqrt(sum_{c in v} phi(c,l,s)^2) + eps), phi = conf_a conf_b (keypoint evidence) and
    conf = sc k(d^2 / s^2) (:func:`roomcap.track.observation.joint_scores`). Rows that equal another pair's
    bit for bit (a camera without any associated joint of the track, :func:`_pair_rows`) are computed once."""
    K, N, J = X.shape[0], X.shape[1], X.shape[2]
    C, L, V = centers.shape[0], limbs.shape[0], pairs.shape[0]
    _check_scores(basis, sc, focal, K, J, C)
    if not (_in_range(limbs, J) and _in_range(pairs, C)):
        raise ValueError("pair_weights: limbs must index joints and pairs cameras")
    out = np.empty((K, V, N), np.float64)
    # limbs per float32 product: each factor lies in [eps, sqrt(2) + eps] (conf <= 1), so eps^g32 stays
    # above float32's smallest normal (1e-38) and (sqrt(2) + eps)^g32 far below its largest
    g32 = max(1, min(8, int(30.0 / max(1.0, -math.log10(min(eps, 1.0))))))
    sm2 = _F(sigma_m) * _F(sigma_m)
    spx = _F(sigma_px)
    epsf = _F(eps)
    for k in range(K):
        xt = np.empty((J, 3, _NB), np.float32)
        conf = np.empty((C, J, _NB), np.float32)
        p2 = np.zeros((C + 1, L, _NB), np.float32)  # row C stays 0: the partner of a camera alone
        prod = np.empty(_NB, np.float64)
        pf = np.empty(_NB, np.float32)
        active = np.empty(C, np.bool_)
        for c in range(C):
            active[c] = False
            for j in range(J):
                if sc[k, c, j] != 0:
                    active[c] = True
        rep, slot = _pair_rows(pairs, active, C)
        for n0 in range(0, N, _NB):
            nb = min(_NB, N - n0)
            for i in range(nb):  # samples innermost from here on
                for j in range(J):
                    xt[j, 0, i] = X[k, n0 + i, j, 0]
                    xt[j, 1, i] = X[k, n0 + i, j, 1]
                    xt[j, 2, i] = X[k, n0 + i, j, 2]
            for c in range(C):
                if not active[c]:
                    continue
                _camera_conf(basis, centers, sc, focal, k, c, C, xt, nb, sm2, spx, conf)
                for li in range(L):
                    a, b = limbs[li, 0], limbs[li, 1]
                    for i in range(nb):
                        t = conf[c, a, i] * conf[c, b, i]  # phi(c,l,s) (eq. 5.8, keypoint evidence)
                        p2[c, li, i] = t * t
            for v in range(V):
                if rep[v] != v:  # the same bits as an earlier row
                    for i in range(nb):
                        out[k, v, n0 + i] = out[k, rep[v], n0 + i]
                    continue
                ca, cb = slot[v, 0], slot[v, 1]
                for i in range(nb):
                    prod[i] = 1.0
                for l0 in range(0, L, g32):  # float32 products of g32 limbs, then one float64 product
                    for i in range(nb):
                        pf[i] = 1.0
                    for li in range(l0, min(L, l0 + g32)):
                        for i in range(nb):
                            pf[i] *= np.sqrt(p2[ca, li, i] + p2[cb, li, i]) + epsf
                    for i in range(nb):
                        prod[i] *= np.float64(pf[i])
                for i in range(nb):
                    out[k, v, n0 + i] = prod[i]
    return out


@njit(cache=True, nogil=True, error_model="numpy")
def sus_indices(phi, counts, u):
    """Eq. 5.6 + stochastic universal resampling per row. phi: (K,V,N) unnormalised weights (>= 0);
    counts: (V,) samples each pair draws (summing to N); u: (K*V,) uniform offsets in [0, 1). Returns
    (K,N) indices into each track's samples, the V rows' draws in order (as
    :func:`roomcap.track.observation.resample_pairs`: index = first i with cdf_i >= (u + m) / count)."""
    K, V, N = phi.shape
    total = 0
    for v in range(counts.shape[0]):
        total += max(counts[v], -N - 1)
    if counts.shape[0] != V or u.shape[0] != K * V or not _in_range(counts, N + 1) or total != N:
        raise ValueError("sus_indices: counts (V,) must sum to N and u have K*V entries")
    idx = np.empty((K, N), np.int64)
    cdf = np.empty((V, N), np.float64)
    acc = np.zeros(8, np.float64)
    for k in range(K):
        for v0 in range(0, V, 8):  # 8 rows' running sums interleaved: independent additions in flight
            nv = min(8, V - v0)
            acc[:] = 0.0
            for i in range(N):
                for r in range(nv):
                    acc[r] += phi[k, v0 + r, i]
                    cdf[v0 + r, i] = acc[r]
        o = 0
        for v in range(V):
            tot = cdf[v, N - 1]
            m = counts[v]
            if not (tot > 0.0 and np.isfinite(tot)):  # degenerate row: uniform weights
                for i in range(N):
                    cdf[v, i] = (i + 1.0) / N
                tot = 1.0
            lo = 0
            for q in range(m):  # binary search: first i with cdf_i >= pos (side='left'), at most N - 1
                pos = (u[k * V + v] + q) / m * tot  # increasing in q: the search starts at the last answer
                hi = N
                while lo < hi:
                    mid = (lo + hi) >> 1
                    if cdf[v, mid] < pos:
                        lo = mid + 1
                    else:
                        hi = mid
                idx[k, o + q] = min(lo, N - 1)
            o += m
    return idx


@njit(cache=True, error_model="numpy", inline="always")
def _guided_offsets(basis, centers, sc, k, j, C, lam, x, tg):
    """Into ``tg`` (3,N): for each sample's joint ``x`` (3,N) of track ``k``, joint ``j``, the offset to
    argmin_x' sum_c s_c |x' - ray_c|^2 + lam |x' - x|^2 (the rays of the track's detections), closed form."""
    N = x.shape[1]
    a00 = a01 = a02 = a11 = a12 = a22 = b0 = b1 = b2 = 0.0  # A = sum s (I - r r^T), b = A c
    for c in range(C):
        s = np.float64(sc[k, c, j])
        if s == 0:
            continue
        r0 = np.float64(basis[k, j, 2 * C + c, 0])
        r1 = np.float64(basis[k, j, 2 * C + c, 1])
        r2 = np.float64(basis[k, j, 2 * C + c, 2])
        c0, c1, c2 = (
            np.float64(centers[c, 0]),
            np.float64(centers[c, 1]),
            np.float64(centers[c, 2]),
        )
        a00 += s * (1.0 - r0 * r0)
        a11 += s * (1.0 - r1 * r1)
        a22 += s * (1.0 - r2 * r2)
        a01 -= s * r0 * r1
        a02 -= s * r0 * r2
        a12 -= s * r1 * r2
        rc = r0 * c0 + r1 * c1 + r2 * c2
        b0 += s * (c0 - r0 * rc)
        b1 += s * (c1 - r1 * rc)
        b2 += s * (c2 - r2 * rc)
    a00, a11, a22 = a00 + lam, a11 + lam, a22 + lam
    i00, i01, i02 = a11 * a22 - a12 * a12, a02 * a12 - a01 * a22, a01 * a12 - a02 * a11
    i11, i12, i22 = a00 * a22 - a02 * a02, a01 * a02 - a00 * a12, a00 * a11 - a01 * a01
    det = a00 * i00 + a01 * i01 + a02 * i02  # the symmetric inverse by its adjugate
    i00, i01, i02, i11, i12, i22 = (
        i00 / det,
        i01 / det,
        i02 / det,
        i11 / det,
        i12 / det,
        i22 / det,
    )
    for n in range(N):
        y0, y1, y2 = b0 + lam * x[0, n], b1 + lam * x[1, n], b2 + lam * x[2, n]
        tg[0, n] = _F(i00 * y0 + i01 * y1 + i02 * y2) - x[0, n]
        tg[1, n] = _F(i01 * y0 + i11 * y1 + i12 * y2) - x[1, n]
        tg[2, n] = _F(i02 * y0 + i12 * y1 + i22 * y2) - x[2, n]


@njit(cache=True, error_model="numpy", inline="always")
def _score_candidates(basis, centers, sc, focal, k, j, c, C, x, e, xm, tot, ys, sm2, spx):
    """Adds camera ``c``'s confidence of the current positions ``x`` (3,N) and of the candidates ``x + e``
    (R,3,N) of track ``k``'s joint ``j`` to ``tot`` (R+1,N); the tolerance at the samples' mean ``xm``."""
    N, R = x.shape[1], e.shape[0]
    half, one, near = _F(0.5), _F(1.0), _F(0.05)
    xm0, xm1, xm2 = xm
    s = sc[k, c, j]
    if s == 0:
        return
    u0, u1, u2, w0, w1, w2, r0, r1, r2, ou, ow, orr = _ray_rows(basis, centers, k, j, c, C)
    along = _F(r0 * xm0 + r1 * xm1 + r2 * xm2 - orr)  # one tolerance per track, joint and camera
    if not along > near:
        return
    gd = spx * along / _F(focal[c])
    sca = np.sqrt(half / (sm2 + gd * gd))  # folds 1 / (2 s^2) into the ray frame
    u0, u1, u2, w0, w1, w2 = u0 * sca, u1 * sca, u2 * sca, w0 * sca, w1 * sca, w2 * sca
    for n in range(N):
        yu = u0 * x[0, n] + u1 * x[1, n] + u2 * x[2, n] - ou * sca
        yw = w0 * x[0, n] + w1 * x[1, n] + w2 * x[2, n] - ow * sca
        ys[0, n], ys[1, n] = yu, yw
        tot[0, n] += s / (one + yu * yu + yw * yw)  # s / (1 + d^2 / 2 s^2)
    for r in range(R):
        for n in range(N):
            e0, e1, e2 = e[r, 0, n], e[r, 1, n], e[r, 2, n]
            du = ys[0, n] + u0 * e0 + u1 * e1 + u2 * e2
            dw = ys[1, n] + w0 * e0 + w1 * e1 + w2 * e2
            tot[r + 1, n] += s / (one + du * du + dw * dw)


@njit(cache=True, nogil=True, error_model="numpy")
def _gather_resampled(X, idx, out):
    """out[k, n] = X[k, idx[k, n]], element by element (an array-to-array slice assignment costs seconds
    of compile)."""
    K, N, J = X.shape[0], X.shape[1], X.shape[2]
    for k in range(K):
        for n in range(N):
            m = idx[k, n]
            for j in range(J):
                for a in range(3):
                    out[k, n, j, a] = X[k, m, j, a]


@njit(cache=True, nogil=True, error_model="numpy")
def refine_resampled(
    X, idx, centers, basis, sc, focal, *, sigma_m, sigma_px, noise, scales, n_guided, lam, refine
):
    """The resampled samples X[k, idx[k]] refined joint by joint (sec. 5.2.2).

    X: (K,N,J,3) float32; idx: (K,N); noise: (K,J,3,R,N) standard normals (R = M - 1 candidates besides
    the current position); scales: (R,) their spreads; the last ``n_guided`` candidates are drawn around
    the point the track's detections put the joint at (:func:`roomcap.track.observation.guided_targets`,
    spread scales / 4). A candidate replaces the joint when its confidence summed over cameras is higher (ties
    keep the current position); the tolerance uses the mean depth of the samples per track, joint and
    camera, as :func:`roomcap.track.observation.refine_joints`. With ``refine`` False only the gather is done.
    Returns X' (K,N,J,3) float32 and the kept joints' summed confidence (K,J,N) float32.
    """
    K, N, J = X.shape[0], X.shape[1], X.shape[2]
    C = centers.shape[0]
    R = noise.shape[3]
    _check_scores(basis, sc, focal, K, J, C)
    if idx.shape != (K, N) or not _in_range(idx, N):
        raise ValueError("refine_resampled: idx must be (K,N) indices into the samples")
    if refine and (noise.shape != (K, J, 3, R, N) or scales.shape[0] < R):
        raise ValueError("refine_resampled: noise must be (K,J,3,R,N) with R scales")
    G = min(n_guided, R)
    out = np.empty((K, N, J, 3), np.float32)
    score = np.zeros((K, J, N), np.float32)
    if not refine:
        _gather_resampled(X, idx, out)
        return out, score
    sm2, spx, one = _F(sigma_m) * _F(sigma_m), _F(sigma_px), _F(1.0)
    for k in range(K):
        x = np.empty((3, N), np.float32)
        e = np.empty((R, 3, N), np.float32)  # candidate offsets
        tot = np.empty((R + 1, N), np.float32)  # summed confidence of candidate 0 (current) and the others
        ys = np.empty((2, N), np.float32)
        tg = np.empty((3, N), np.float32)  # guided target - current position
        for j in range(J):
            for n in range(N):
                m = idx[k, n]
                x[0, n], x[1, n], x[2, n] = X[k, m, j, 0], X[k, m, j, 1], X[k, m, j, 2]
            for r in range(R):
                s_r = _F(scales[r]) * (_F(0.25) if r >= R - G else one)
                for a in range(3):
                    for n in range(N):
                        e[r, a, n] = noise[k, j, a, r, n] * s_r
            if G > 0:  # guided: argmin_x' sum_c s_c |x' - ray_c|^2 + lam |x' - x|^2, closed form
                _guided_offsets(basis, centers, sc, k, j, C, lam, x, tg)
                for r in range(R - G, R):
                    for a in range(3):
                        for n in range(N):
                            e[r, a, n] += tg[a, n]
            tot[:] = 0
            xm0 = xm1 = xm2 = 0.0  # the samples' mean joint: its depth is their mean depth in each camera
            for n in range(N):
                xm0 += x[0, n]
                xm1 += x[1, n]
                xm2 += x[2, n]
            xm0, xm1, xm2 = xm0 / N, xm1 / N, xm2 / N
            for c in range(C):
                _score_candidates(
                    basis, centers, sc, focal, k, j, c, C, x, e, (xm0, xm1, xm2), tot, ys, sm2, spx
                )
            for n in range(N):
                best, tb = -1, tot[0, n]  # the current position wins ties
                for r in range(R):
                    if tot[r + 1, n] > tb:
                        best, tb = r, tot[r + 1, n]
                score[k, j, n] = tb
                if best >= 0:
                    for a in range(3):
                        out[k, n, j, a] = x[a, n] + e[best, a, n]
                else:
                    for a in range(3):
                        out[k, n, j, a] = x[a, n]
    return out, score


@njit(cache=True, nogil=True, error_model="numpy")
def output_stats(X, score, has, eps):
    """Sec. 5.2.4: the weighted mean pose (K,J,3) and per-joint spread std_m (K,J) (per-axis RMS), with
    weights prod_j (score + eps) for the tracks with ``has`` (K,) (the refinement's summed confidences
    (K,J,N)) and uniform weights for the others. As :func:`roomcap.track.observation.weighted_stats` with
    ``log_phi = sum_j log(score + eps)``; the product runs in float64 over groups of 8 joints."""
    K, N, J = X.shape[0], X.shape[1], X.shape[2]
    mean = np.empty((K, J, 3), np.float32)
    if score.shape != (K, J, N) or has.shape[0] != K:
        raise ValueError("output_stats: score must be (K,J,N) and has (K,)")
    std = np.empty((K, J), np.float32)
    lp = np.empty(N, np.float64)
    p = np.empty(N, np.float64)
    w = np.empty(N, np.float64)
    m = np.empty(J * 3, np.float64)
    d2 = np.empty(J, np.float64)
    for k in range(K):
        if has[k]:
            lp[:] = 0.0
            for j0 in range(0, J, 8):
                p[:] = 1.0
                for j in range(j0, min(J, j0 + 8)):
                    for n in range(N):
                        p[n] *= np.float64(score[k, j, n] + _F(eps))
                for n in range(N):
                    lp[n] += math.log(p[n])
            mx = lp[0]
            for n in range(1, N):  # the maximum as a loop (np.max costs a second of compile); NaN wins
                if (lp[n] > mx or lp[n] != lp[n]) and mx == mx:
                    mx = lp[n]
            tot = 0.0
            for n in range(N):
                w[n] = math.exp(lp[n] - mx)
                tot += w[n]
            for n in range(N):
                w[n] /= tot
        else:
            w[:] = 1.0 / N
        Xk = X[k].reshape(N, J * 3)
        m[:] = 0.0
        for n in range(N):  # joints and axes innermost: one vector of sums per sample
            wn = w[n]
            for q in range(J * 3):
                m[q] += wn * Xk[n, q]
        d2[:] = 0.0
        for n in range(N):
            wn = w[n]
            for j in range(J):
                a0, a1, a2 = (
                    Xk[n, 3 * j] - m[3 * j],
                    Xk[n, 3 * j + 1] - m[3 * j + 1],
                    Xk[n, 3 * j + 2] - m[3 * j + 2],
                )
                d2[j] += wn * (a0 * a0 + a1 * a1 + a2 * a2)
        for j in range(J):
            mean[k, j, 0], mean[k, j, 1], mean[k, j, 2] = m[3 * j], m[3 * j + 1], m[3 * j + 2]
            std[k, j] = math.sqrt(d2[j] / 3.0)
    return mean, std


@njit(cache=True, nogil=True, error_model="numpy")
def ray_basis(Minv, kp):
    """Orthonormal frames of the keypoints' viewing rays, as :func:`roomcap.track.observation.ray_basis`.
    Minv: (C,3,3) float32; kp: (K,C,J,2) undistorted px (NaN = 0) -> B (K,J,3C,3) float32, rows
    [u_0..u_{C-1}, w_0..w_{C-1}, r_0..r_{C-1}] with r_c the unit ray and u_c, w_c perpendicular to it."""
    K, C, J = kp.shape[0], kp.shape[1], kp.shape[2]
    if Minv.shape != (C, 3, 3):
        raise ValueError("ray_basis: Minv must be (C,3,3)")
    out = np.empty((K, J, 3 * C, 3), np.float32)
    for k in range(K):
        for c in range(C):
            for j in range(J):
                a, b = kp[k, c, j, 0], kp[k, c, j, 1]
                a = a if np.isfinite(a) else _F(0.0)
                b = b if np.isfinite(b) else _F(0.0)
                r0 = Minv[c, 0, 0] * a + Minv[c, 0, 1] * b + Minv[c, 0, 2]
                r1 = Minv[c, 1, 0] * a + Minv[c, 1, 1] * b + Minv[c, 1, 2]
                r2 = Minv[c, 2, 0] * a + Minv[c, 2, 1] * b + Minv[c, 2, 2]
                nr = np.sqrt(r0 * r0 + r1 * r1 + r2 * r2)
                r0, r1, r2 = r0 / nr, r1 / nr, r2 / nr
                if abs(r2) < _F(0.9):  # u = r x helper, helper = z (or x for a ray along z)
                    u0, u1, u2 = r1, -r0, _F(0.0)
                else:
                    u0, u1, u2 = _F(0.0), r2, -r1
                nu = np.sqrt(u0 * u0 + u1 * u1 + u2 * u2)
                u0, u1, u2 = u0 / nu, u1 / nu, u2 / nu
                out[k, j, c, 0], out[k, j, c, 1], out[k, j, c, 2] = u0, u1, u2
                out[k, j, C + c, 0] = r1 * u2 - r2 * u1  # w = r x u
                out[k, j, C + c, 1] = r2 * u0 - r0 * u2
                out[k, j, C + c, 2] = r0 * u1 - r1 * u0
                out[k, j, 2 * C + c, 0], out[k, j, 2 * C + c, 1], out[k, j, 2 * C + c, 2] = r0, r1, r2
    return out


@njit(cache=True, nogil=True, error_model="numpy")
def association_costs(mean_uv, mean_depth, det_kp, det_sc, *, focal, tol_m, min_joints, min_score, gate):
    """The cost of every track-detection pair per camera, as
    :func:`roomcap.track.observation.association_costs`:
    the median over joints of the image distance in units of ``tol_m`` seen at the joint's depth, on the
    joints both have (at least ``min_joints``, else inf). mean_uv: (C,K,J,2), mean_depth: (C,K,J), det_kp:
    (C,D,J,2), det_sc: (C,D,J), focal: (C,); gate: (K,) -> (C,K,D) float64. Where fewer than half the joints
    lie within the track's gate the median reaches it and is not computed: inf (the same assignment)."""
    C, K, J = mean_uv.shape[0], mean_uv.shape[1], mean_uv.shape[2]
    D = det_kp.shape[1]
    if (
        mean_depth.shape != (C, K, J)
        or det_kp.shape != (C, D, J, 2)
        or det_sc.shape != (C, D, J)
        or focal.shape[0] != C
        or gate.shape[0] != K
    ):
        raise ValueError("association_costs: shapes do not agree")
    cost = np.empty((C, K, D), np.float64)
    v = np.empty(J, np.float64)
    scale = np.empty(J, np.float64)
    lo, msc = _F(0.1), _F(min_score)  # compared in float32, as numpy compares a float32 array with a float
    for c in range(C):
        for k in range(K):
            g = gate[k]
            for j in range(J):
                scale[j] = np.float64(focal[c]) * tol_m / max(np.float64(mean_depth[c, k, j]), 0.1)
            for d in range(D):
                m, below = 0, 0
                for j in range(J):
                    a, b = det_kp[c, d, j, 0], det_kp[c, d, j, 1]
                    if not (mean_depth[c, k, j] > lo and np.isfinite(a) and np.isfinite(b)):
                        continue
                    if not det_sc[c, d, j] >= msc:
                        continue
                    du, dv = mean_uv[c, k, j, 0] - a, mean_uv[c, k, j, 1] - b
                    r = np.sqrt(du * du + dv * dv) / scale[j]
                    if np.isfinite(r):
                        v[m] = r
                        m += 1
                        below += r < g
                # the median (v_lo + v_hi) / 2 is below the gate only if v_lo is: (m-1)//2 + 1 values below
                if m < max(min_joints, 1) or below <= (m - 1) // 2:
                    cost[c, k, d] = np.inf
                    continue
                for i in range(1, m):  # insertion sort of the m values
                    x = v[i]
                    t = i
                    while t > 0 and v[t - 1] > x:
                        v[t] = v[t - 1]
                        t -= 1
                    v[t] = x
                cost[c, k, d] = (v[(m - 1) // 2] + v[m // 2]) / 2
    return cost


@njit(cache=True, nogil=True, error_model="numpy")
def gather_rows(a, idx):
    """a[idx] for a (B,F) float32 array: the resampling's gather of the motion state."""
    F = a.shape[1]
    if not _in_range(idx, a.shape[0]):
        raise ValueError("gather_rows: index out of range")
    out = np.empty((idx.shape[0], F), np.float32)
    for i in range(idx.shape[0]):
        j = idx[i]
        for f in range(F):
            out[i, f] = a[j, f]
    return out


def gather_state(state: dict, idx: np.ndarray) -> dict:
    """:func:`roomcap.track.priors.gather_state` with float32 states gathered by :func:`gather_rows`."""
    out = {}
    idx = np.ascontiguousarray(idx, np.int64)
    for k, v in state.items():
        if v.dtype == np.float32 and v.ndim >= 1 and v.flags.c_contiguous and len(v):
            out[k] = gather_rows(v.reshape(len(v), -1), idx).reshape((len(idx),) + v.shape[1:])
        else:
            out[k] = v[idx]
    return out


# --- the GRU motion prior (eq. 5.1-5.5) ----------------------------------------------------------------
