"""Affine Lucas-Kanade refinement of track positions against the reference (numba).

Per track (``nogil``: the caller runs slices of the tracks in threads): the template is the reference image's (2r+1)^2 patch
around the track's reference position; the warp maps a template offset d to ``M [d; 1]`` in
the frame, starting from the track's position and the local affine map of the dense flow
(``A = I + grad flow`` at the reference position, central differences over +-2 px).  Inverse
compositional Gauss-Newton on the six affine parameters (Baker and Matthews 2004): the
template's steepest-descent images and the 6x6 Gauss-Newton matrix are computed once per
track, each iteration samples the frame at the warped patch and composes the warp with the
inverse of the update.  The zero-mean normalised cross-correlation of the template with the
warped patch is measured at the start and at the end; the refined position is kept only where
it moved less than ``max_move`` px, stayed in the frame and the correlation rose, so a
refinement cannot make a track worse by its own measure.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def _bilinear(img: np.ndarray, x: float, y: float) -> float:
    """``img`` (H, W) at (x, y), the border replicated."""
    h, w = img.shape
    x = min(max(x, 0.0), w - 1.0)
    y = min(max(y, 0.0), h - 1.0)
    x0 = min(int(x), w - 2) if w > 1 else 0
    y0 = min(int(y), h - 2) if h > 1 else 0
    ax, ay = x - x0, y - y0
    x1, y1 = min(x0 + 1, w - 1), min(y0 + 1, h - 1)
    top = img[y0, x0] * (1.0 - ax) + img[y0, x1] * ax
    bot = img[y1, x0] * (1.0 - ax) + img[y1, x1] * ax
    return top * (1.0 - ay) + bot * ay


@njit(cache=True, nogil=True)
def _solve6(H: np.ndarray, b: np.ndarray, out: np.ndarray) -> bool:
    """out = H^-1 b for a symmetric positive definite 6x6 H (Cholesky, H overwritten with
    its factor); False where H is not positive definite."""
    n = 6
    for j in range(n):
        s = H[j, j]
        for k in range(j):
            s -= H[j, k] * H[j, k]
        if s <= 1e-12:
            return False
        d = math.sqrt(s)
        H[j, j] = d
        for i in range(j + 1, n):
            t = H[i, j]
            for k in range(j):
                t -= H[i, k] * H[j, k]
            H[i, j] = t / d
    for i in range(n):
        t = b[i]
        for k in range(i):
            t -= H[i, k] * out[k]
        out[i] = t / H[i, i]
    for i in range(n - 1, -1, -1):
        t = out[i]
        for k in range(i + 1, n):
            t -= H[k, i] * out[k]
        out[i] = t / H[i, i]
    return True


@njit(cache=True, nogil=True)
def refine(ref: np.ndarray, ref_gx: np.ndarray, ref_gy: np.ndarray, frame: np.ndarray,
           flow: np.ndarray, p0: np.ndarray, p: np.ndarray, radius: int, iterations: int,
           max_move: float, out: np.ndarray, zncc: np.ndarray) -> None:
    """Refined positions ``out`` (P, 2) of the tracks at ``p`` (P, 2) in ``frame`` whose
    reference positions are ``p0`` (P, 2) in ``ref`` (float32 (H, W), contrast-normalised
    like ``frame``; ``ref_gx``, ``ref_gy`` its x and y derivatives); ``flow`` (H, W, 2) the
    dense reference->frame flow (for the local affine start); ``zncc`` (P,) the template's
    correlation with the frame at the kept position."""
    n = (2 * radius + 1) ** 2
    T = np.empty(n)
    gx = np.empty(n)
    gy = np.empty(n)
    dx = np.empty(n)
    dy = np.empty(n)
    Iw = np.empty(n)
    H = np.empty((6, 6))
    Hf = np.empty((6, 6))
    sd = np.empty(6)
    b6 = np.empty(6)
    dq = np.empty(6)
    m = np.empty(6)
    for t in range(p.shape[0]):
        _refine_one(ref, ref_gx, ref_gy, frame, flow, p0, p, radius, iterations, max_move, out,
                    zncc, t, T, gx, gy, dx, dy, Iw, H, Hf, sd, b6, dq, m)


@njit(cache=True, nogil=True)
def _refine_one(ref, ref_gx, ref_gy, frame, flow, p0, p, radius, iterations, max_move, out,
                zncc, t, T, gx, gy, dx, dy, Iw, H, Hf, sd, b6, dq, m):  # noqa: ANN001
    """``refine`` of track ``t``; T .. m: work arrays of the template's size and 6."""
    n = T.size
    x0, y0, x, y = p0[t, 0], p0[t, 1], p[t, 0], p[t, 1]
    out[t, 0], out[t, 1] = x, y
    zncc[t] = 0.0
    k = 0
    for j in range(-radius, radius + 1):
        for i in range(-radius, radius + 1):
            T[k] = _bilinear(ref, x0 + i, y0 + j)
            gx[k] = _bilinear(ref_gx, x0 + i, y0 + j)
            gy[k] = _bilinear(ref_gy, x0 + i, y0 + j)
            dx[k], dy[k] = i, j
            k += 1
    tm = T.mean()
    tn = 0.0
    for k in range(n):
        tn += (T[k] - tm) ** 2
    if tn <= 1e-9:
        return
    tn = math.sqrt(tn)
    # Gauss-Newton matrix of the steepest-descent images [gx dx, gy dx, gx dy, gy dy, gx, gy]
    H[:, :] = 0.0
    for k in range(n):
        sd[0], sd[1] = gx[k] * dx[k], gy[k] * dx[k]
        sd[2], sd[3] = gx[k] * dy[k], gy[k] * dy[k]
        sd[4], sd[5] = gx[k], gy[k]
        for a in range(6):
            for b in range(a + 1):
                H[a, b] += sd[a] * sd[b]
    for a in range(6):
        H[a, a] += 1e-3
        for b in range(a):
            H[b, a] = H[a, b]
    # the local affine map of the flow at the reference position (+-2 px)
    fu, fv = flow[:, :, 0], flow[:, :, 1]
    a11 = 1.0 + (_bilinear(fu, x0 + 2, y0) - _bilinear(fu, x0 - 2, y0)) / 4
    a12 = (_bilinear(fu, x0, y0 + 2) - _bilinear(fu, x0, y0 - 2)) / 4
    a21 = (_bilinear(fv, x0 + 2, y0) - _bilinear(fv, x0 - 2, y0)) / 4
    a22 = 1.0 + (_bilinear(fv, x0, y0 + 2) - _bilinear(fv, x0, y0 - 2)) / 4
    m[0], m[1], m[2], m[3], m[4], m[5] = a11, a12, x, a21, a22, y
    z_start = 0.0
    ok = True
    for it in range(iterations + 1):
        for k in range(n):
            Iw[k] = _bilinear(frame, m[0] * dx[k] + m[1] * dy[k] + m[2],
                              m[3] * dx[k] + m[4] * dy[k] + m[5])
        if it == 0:
            z_start = _zncc(T, tm, tn, Iw)
        if it == iterations:
            break
        for a in range(6):
            b6[a] = 0.0
        for k in range(n):
            e = Iw[k] - T[k]
            b6[0] += gx[k] * dx[k] * e
            b6[1] += gy[k] * dx[k] * e
            b6[2] += gx[k] * dy[k] * e
            b6[3] += gy[k] * dy[k] * e
            b6[4] += gx[k] * e
            b6[5] += gy[k] * e
        Hf[:, :] = H
        if not _solve6(Hf, b6, dq):
            ok = False
            break
        # M <- M o W(dq)^-1, W(dq) = [[1 + q0, q2, q4], [q1, 1 + q3, q5]]
        det = (1.0 + dq[0]) * (1.0 + dq[3]) - dq[1] * dq[2]
        if abs(det) < 1e-6:
            ok = False
            break
        i00, i01 = (1.0 + dq[3]) / det, -dq[2] / det
        i10, i11 = -dq[1] / det, (1.0 + dq[0]) / det
        i02 = -(i00 * dq[4] + i01 * dq[5])
        i12 = -(i10 * dq[4] + i11 * dq[5])
        r0 = (m[0] * i00 + m[1] * i10, m[0] * i01 + m[1] * i11,
              m[0] * i02 + m[1] * i12 + m[2])
        r1 = (m[3] * i00 + m[4] * i10, m[3] * i01 + m[4] * i11,
              m[3] * i02 + m[4] * i12 + m[5])
        m[0], m[1], m[2] = r0
        m[3], m[4], m[5] = r1
    zncc[t] = z_start
    if not ok:
        return
    z_end = _zncc(T, tm, tn, Iw)
    move = math.hypot(m[2] - x, m[5] - y)
    inside = 0.0 <= m[2] <= frame.shape[1] - 1 and 0.0 <= m[5] <= frame.shape[0] - 1
    if math.isfinite(move) and move < max_move and z_end > z_start and inside:
        out[t, 0], out[t, 1] = m[2], m[5]
        zncc[t] = z_end


@njit(cache=True, nogil=True)
def _zncc(T: np.ndarray, tm: float, tn: float, Iw: np.ndarray) -> float:
    n = T.size
    im = Iw.mean()
    cov = 0.0
    var = 0.0
    for k in range(n):
        a = Iw[k] - im
        cov += (T[k] - tm) * a
        var += a * a
    return cov / (tn * math.sqrt(var) + 1e-9)
