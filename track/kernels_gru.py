"""The GRU prior's compiled kernels (eq. 5.1–5.5, :class:`roomcap.track.priors.GRUCellPrior`): the inputs in
the hip frame (eq. 5.2–5.4), the cell's gates after its two matrix products, and the displacement turned back
into the world (eq. 5.5). Arithmetic and caching as :mod:`roomcap.track.kernels` (float32 as the numpy path,
the rows on numba's threads, the same bits for any number of threads)."""

from __future__ import annotations

import numpy as np
from llvmlite import ir
from numba import njit, types
from numba.extending import intrinsic

from roomcap.track.kernels import _F


@njit(cache=True, nogil=True, error_model="numpy")
def gru_inputs(x, prev, ip, il, ir, vscale):
    """Eq. 5.2–5.4 for a batch: x, prev (B,J,3) float32 (the samples and their previous positions) ->
    inp (B,2·J·3) = [R(x - origin), R(x - prev)·vscale] flattened, and (cos, sin) of each sample's facing
    angle (B,2). The origin is the pelvis (mid-hips where it is NaN); theta = atan2 of right - left hip
    (0 where unknown), as :func:`roomcap.track.normalize.hip_frame`; its cosine and sine are the hip
    direction's components over its length."""
    B, J = x.shape[0], x.shape[1]
    inp = np.empty((B, 2 * J * 3), np.float32)
    if prev.shape != x.shape or max(ip, il, ir) >= J or min(ip, il, ir) < 0:
        raise ValueError("gru_inputs: prev must be shaped as x and the hip joints index it")
    cs = np.empty((B, 2), np.float32)
    vs = _F(vscale)
    for b in range(B):
        o0, o1, o2 = x[b, ip, 0], x[b, ip, 1], x[b, ip, 2]
        h = _F(0.5)
        if not np.isfinite(o0):
            o0 = h * (x[b, il, 0] + x[b, ir, 0])
        if not np.isfinite(o1):
            o1 = h * (x[b, il, 1] + x[b, ir, 1])
        if not np.isfinite(o2):
            o2 = h * (x[b, il, 2] + x[b, ir, 2])
        dx, dy = x[b, ir, 0] - x[b, il, 0], x[b, ir, 1] - x[b, il, 1]
        nd = np.sqrt(dx * dx + dy * dy)  # cos, sin of theta = atan2(dy, dx) without the trigonometry
        if nd > 0 and np.isfinite(nd):
            c, s = dx / nd, dy / nd
        else:  # theta = 0 (as atan2(0, 0); unknown hips)
            c, s = _F(1.0), _F(0.0)
        cs[b, 0], cs[b, 1] = c, s
        for j in range(J):
            a0, a1, a2 = x[b, j, 0] - o0, x[b, j, 1] - o1, x[b, j, 2] - o2
            inp[b, 3 * j] = c * a0 + s * a1  # eq. 5.3: R v = [c v0 + s v1, c v1 - s v0, v2]
            inp[b, 3 * j + 1] = c * a1 - s * a0
            inp[b, 3 * j + 2] = a2
            v0, v1, v2 = x[b, j, 0] - prev[b, j, 0], x[b, j, 1] - prev[b, j, 1], x[b, j, 2] - prev[b, j, 2]
            if vs != _F(1.0):
                v0, v1, v2 = v0 * vs, v1 * vs, v2 * vs
            inp[b, 3 * (J + j)] = c * v0 + s * v1
            inp[b, 3 * (J + j) + 1] = c * v1 - s * v0
            inp[b, 3 * (J + j) + 2] = v2
    return inp, cs


@intrinsic
def _f32_from_bits(typingctx, i):
    """The float32 whose bits are the int32 ``i`` (LLVM bitcast; vectorises, unlike ldexp)."""
    sig = types.float32(types.int32)

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.FloatType())

    return sig, codegen


@njit(cache=True, error_model="numpy", inline="always")
def _exp(x):
    """e^x for float32 x in [-87, 88] (clamped): x = n ln2 + r (Cody-Waite), e^r by Cephes expf's degree-6
    polynomial, times 2^n from its bits. Within 1 ulp of the exact value (numpy's SIMD expf: 2.4 ulp) and it
    vectorises (math.exp is a scalar libm call)."""
    x = min(max(x, _F(-87.0)), _F(88.0))
    n = np.floor(x * _F(1.44269504088896341) + _F(0.5))
    r = x - n * _F(0.693359375)
    r = r - n * _F(-2.12194440e-4)
    p = _F(1.9875691500e-4)
    p = p * r + _F(1.3981999507e-3)
    p = p * r + _F(8.3334519073e-3)
    p = p * r + _F(4.1665795894e-2)
    p = p * r + _F(1.6666665459e-1)
    p = p * r + _F(5.0000001201e-1)
    p = p * r * r + r + _F(1.0)
    return p * _f32_from_bits((np.int32(n) + np.int32(127)) << np.int32(23))


@njit(cache=True, error_model="numpy", inline="always")
def _tanh(x):
    """tanh for float32 x as Cephes tanhf: an odd polynomial for |x| < 0.625, 1 - 2 / (e^{2|x|} + 1) above."""
    a = abs(x)
    big = _F(1.0) - _F(2.0) / (_exp(_F(2.0) * a) + _F(1.0))
    big = big if x >= 0 else -big
    z = x * x
    p = _F(-5.70498872745e-3)
    p = p * z + _F(2.06390887954e-2)
    p = p * z - _F(5.37397155531e-2)
    p = p * z + _F(1.33314422036e-1)
    p = p * z - _F(3.33332819422e-1)
    small = p * z * x + x
    return big if a >= _F(0.625) else small


@njit(cache=True, nogil=True, error_model="numpy")
def gru_gates(gi, b_ih, gh, b_hh, h, mask):
    """The GRU cell after its two products gi = x W_ih, gh = h W_hh (B,3H), gates r, z, n (torch.nn.GRUCell):
    r = sigma(gi_r + b_ir + gh_r + b_hr), z likewise, n = tanh(gi_n + b_in + r (gh_n + b_hn)),
    h' = (1 - z) n + z h. mask: (B,H) MC-dropout mask already scaled (eq. 5.1's dropout kept on at
    inference), or (0,0) for none. Returns h' and h' * mask (the output layer's input), (B,H) float32."""
    B, H = h.shape
    if gi.shape != (B, 3 * H) or gh.shape != (B, 3 * H) or b_ih.shape[0] != 3 * H or b_hh.shape[0] != 3 * H:
        raise ValueError("gru_gates: gi, gh must be (B,3H) and the biases (3H,)")
    if mask.shape[0] and mask.shape != (B, H):
        raise ValueError("gru_gates: mask must be (B,H) or empty")
    out = np.empty((B, H), np.float32)
    dropped = np.empty((B, H), np.float32) if mask.shape[0] else out
    one = _F(1.0)
    for b in range(B):
        for i in range(H):
            r = one / (one + _exp(-((gi[b, i] + b_ih[i]) + (gh[b, i] + b_hh[i]))))
            z = one / (one + _exp(-((gi[b, H + i] + b_ih[H + i]) + (gh[b, H + i] + b_hh[H + i]))))
            n = _tanh((gi[b, 2 * H + i] + b_ih[2 * H + i]) + r * (gh[b, 2 * H + i] + b_hh[2 * H + i]))
            out[b, i] = n + z * (h[b, i] - n)
        if mask.shape[0]:
            for i in range(H):
                dropped[b, i] = out[b, i] * mask[b, i]
    return out, dropped


@njit(cache=True, nogil=True, error_model="numpy")
def gru_outputs(delta, b_out, cs, x, dscale, noise, sigma):
    """Eq. 5.5 for the displacement: x + R^T (delta + b_out)·dscale + sigma·noise. delta (B,3J) = the output
    layer's product, b_out (3J,) its bias, cs (B,2) from :func:`gru_inputs`, x (B,J,3), noise (B,J,3)
    standard normals (ignored for sigma 0) -> (B,J,3) float32."""
    B, J = x.shape[0], x.shape[1]
    out = np.empty((B, J, 3), np.float32)
    if delta.shape != (B, 3 * J) or b_out.shape[0] != 3 * J or cs.shape != (B, 2):
        raise ValueError("gru_outputs: delta must be (B,3J), b_out (3J,) and cs (B,2)")
    if sigma != 0 and noise.shape != x.shape:
        raise ValueError("gru_outputs: noise must be shaped as x")
    ds, sg = _F(dscale), _F(sigma)
    for b in range(B):
        c, s = cs[b, 0], cs[b, 1]
        for j in range(J):
            d0, d1, d2 = (
                delta[b, 3 * j] + b_out[3 * j],
                delta[b, 3 * j + 1] + b_out[3 * j + 1],
                delta[b, 3 * j + 2] + b_out[3 * j + 2],
            )
            if ds != _F(1.0):
                d0, d1, d2 = d0 * ds, d1 * ds, d2 * ds
            o0 = c * d0 - s * d1 + x[b, j, 0]  # R^T v = [c v0 - s v1, c v1 + s v0, v2]
            o1 = c * d1 + s * d0 + x[b, j, 1]
            o2 = d2 + x[b, j, 2]
            if sg != _F(0.0):
                o0 += noise[b, j, 0] * sg
                o1 += noise[b, j, 1] * sg
                o2 += noise[b, j, 2] * sg
            out[b, j, 0], out[b, j, 1], out[b, j, 2] = o0, o1, o2
    return out
