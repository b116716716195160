"""Per-frame sums of the pinhole camera's fits (numba): one pass over a frame's points.

Both were NumPy expressions over (F, P) and (F, 6, 2, P) arrays, a dozen passes over memory
each: ``planar_pinhole.pose_steps`` (36 calls of a planar batch's refinements, 1.4 s of the
80-frame 320x240 flag's 9 s batch call) and ``perspective.frame_errors`` (each batch's depth
sign and ``auto``'s planar test, ~0.24 s a call at 80 frames x 10k tracks).  Here the sums
accumulate in registers, the same values to rounding.  Serial and ``nogil`` as ``_admm``.
"""
from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def pose_normal_equations(O: np.ndarray, m: np.ndarray, w: np.ndarray, R: np.ndarray,
                          T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Gauss-Newton normal equations of the reprojection error of object points O (F, P, 3)
    posed as ``R_f O + T_f`` against normalised image points m (F, P, 2), weights w (F, P):
    J^T J (F, 6, 6) and J^T r (F, 6), the parameters a left rotation vector and the
    translation (``planar_pinhole.pose_steps``); points behind the camera (Z <= 1e-6) count
    nothing."""
    F, P = w.shape
    A = np.zeros((F, 6, 6))
    g = np.zeros((F, 6))
    for f in range(F):
        r00, r01, r02 = R[f, 0, 0], R[f, 0, 1], R[f, 0, 2]
        r10, r11, r12 = R[f, 1, 0], R[f, 1, 1], R[f, 1, 2]
        r20, r21, r22 = R[f, 2, 0], R[f, 2, 1], R[f, 2, 2]
        t0, t1, t2 = T[f, 0], T[f, 1], T[f, 2]
        s00 = s01 = s02 = s03 = s04 = s05 = 0.0
        s11 = s12 = s13 = s14 = s15 = 0.0
        s22 = s23 = s24 = s25 = 0.0
        s33 = s35 = s44 = s45 = s55 = 0.0
        q0 = q1 = q2 = q3 = q4 = q5 = 0.0
        for p in range(P):
            wp = w[f, p]
            if wp == 0.0:
                continue
            o0, o1, o2 = O[f, p, 0], O[f, p, 1], O[f, p, 2]
            a = r00 * o0 + r01 * o1 + r02 * o2
            b = r10 * o0 + r11 * o1 + r12 * o2
            c = r20 * o0 + r21 * o1 + r22 * o2
            X, Y, Z = a + t0, b + t1, c + t2
            if not Z > 1e-6:
                continue
            iz = 1.0 / Z
            wz = wp * iz
            gx = -X * iz * wz                 # weighted d(u)/dZ, d(v)/dZ
            gy = -Y * iz * wz
            ru = (X * iz - m[f, p, 0]) * wp
            rv = (Y * iz - m[f, p, 1]) * wp
            # d(u)/d(pose), d(v)/d(pose): dX, dY, dZ / d(rotation) are the rows of -[RO]x,
            # (0, c, -b), (-c, 0, a), (b, -a, 0); the identity for the translation (u has no
            # dY term, v no dX term)
            u0, u1, u2, u3, u5 = gx * b, wz * c - gx * a, -wz * b, wz, gx
            v0, v1, v2, v4, v5 = gy * b - wz * c, -gy * a, wz * a, wz, gy
            s00 += u0 * u0 + v0 * v0
            s01 += u0 * u1 + v0 * v1
            s02 += u0 * u2 + v0 * v2
            s03 += u0 * u3
            s04 += v0 * v4
            s05 += u0 * u5 + v0 * v5
            s11 += u1 * u1 + v1 * v1
            s12 += u1 * u2 + v1 * v2
            s13 += u1 * u3
            s14 += v1 * v4
            s15 += u1 * u5 + v1 * v5
            s22 += u2 * u2 + v2 * v2
            s23 += u2 * u3
            s24 += v2 * v4
            s25 += u2 * u5 + v2 * v5
            s33 += u3 * u3
            s35 += u3 * u5
            s44 += v4 * v4
            s45 += v4 * v5
            s55 += u5 * u5 + v5 * v5
            q0 += u0 * ru + v0 * rv
            q1 += u1 * ru + v1 * rv
            q2 += u2 * ru + v2 * rv
            q3 += u3 * ru
            q4 += v4 * rv
            q5 += u5 * ru + v5 * rv
        upper = (s00, s01, s02, s03, s04, s05, s11, s12, s13, s14, s15, s22, s23, s24, s25,
                 s33, 0.0, s35, s44, s45, s55)
        k = 0
        for i in range(6):
            for j in range(i, 6):
                A[f, i, j] = upper[k]
                A[f, j, i] = upper[k]
                k += 1
        g[f, 0], g[f, 1], g[f, 2] = q0, q1, q2
        g[f, 3], g[f, 4], g[f, 5] = q3, q4, q5
    return A, g


@njit(cache=True, nogil=True)
def frame_error_table(S: np.ndarray, scale: np.ndarray, t: np.ndarray, W: np.ndarray,
                      V: np.ndarray, focal: float, cx: float, cy: float, lo: float,
                      hi: float) -> np.ndarray:
    """(F, 2) ``perspective.frame_errors``: per frame the V-weighted mean pixel error of the
    shapes S (F, P, 3) (image units x ``scale`` (F,), image translation t (F, 2)) imaged by the
    pinhole camera with their own depths (column 0) and reflected (column 1), each with its
    best image shift; the depth ratio clipped to [lo, hi].  W (2F, P) the tracks."""
    F, P = V.shape
    out = np.empty((F, 2))
    for f in range(F):
        s = scale[f]
        tx, ty = t[f, 0] - cx, t[f, 1] - cy
        vsum = 0.0
        for p in range(P):
            vsum += V[f, p]
        for k in range(2):
            sign = 1.0 if k == 0 else -1.0
            na = nb = den = 0.0
            for p in range(P):
                v = V[f, p]
                r = 1.0 + sign * S[f, p, 2] * s / focal
                a = 1.0 / min(max(r, lo), hi)
                r0 = cx + (S[f, p, 0] * s + tx) * a - W[2 * f, p]
                r1 = cy + (S[f, p, 1] * s + ty) * a - W[2 * f + 1, p]
                na += v * a * r0
                nb += v * a * r1
                den += v * a * a
            den = max(den, 1e-12)
            sx, sy = -na / den, -nb / den
            e = 0.0
            for p in range(P):
                r = 1.0 + sign * S[f, p, 2] * s / focal
                a = 1.0 / min(max(r, lo), hi)
                e0 = cx + (S[f, p, 0] * s + tx) * a - W[2 * f, p] + sx * a
                e1 = cy + (S[f, p, 1] * s + ty) * a - W[2 * f + 1, p] + sy * a
                e += np.sqrt(e0 * e0 + e1 * e1) * V[f, p]
            out[f, k] = e / max(vsum, 1e-12)
    return out


@njit(cache=True, nogil=True)
def reprojection_loss(X: np.ndarray, m: np.ndarray, w: np.ndarray, robust: float) -> float:
    """``planar_pinhole._reprojection``: the w-weighted mean distance of the camera-frame points
    X (F, P, 3) imaged from the normalised points m (F, P, 2), or with ``robust`` > 0 its
    Cauchy loss at that scale; inf when any point is not in front of the camera."""
    F, P = w.shape
    num = 0.0
    den = 0.0
    for f in range(F):
        for p in range(P):
            z = X[f, p, 2]
            if not z > 0.0:
                return np.inf
            du = X[f, p, 0] / z - m[f, p, 0]
            dv = X[f, p, 1] / z - m[f, p, 1]
            e = np.sqrt(du * du + dv * dv)
            if robust > 0.0:
                e = robust * np.log1p((e / robust) ** 2)
            num += e * w[f, p]
            den += w[f, p]
    return num / max(den, 1e-12)


@njit(cache=True, nogil=True)
def cauchy_weights(rest: np.ndarray, h: np.ndarray, R: np.ndarray, T: np.ndarray,
                   m: np.ndarray, w0: np.ndarray, robust: float) -> np.ndarray:
    """``planar_pinhole._cauchy``: w0 (F, P) x the Cauchy weight at ``robust`` of each point's
    reprojection error, the object points (rest (P, 2), heights h (F, P)) posed by R, T."""
    F, P = w0.shape
    out = np.empty((F, P))
    for f in range(F):
        for p in range(P):
            x, y, z = rest[p, 0], rest[p, 1], h[f, p]
            X = R[f, 0, 0] * x + R[f, 0, 1] * y + R[f, 0, 2] * z + T[f, 0]
            Y = R[f, 1, 0] * x + R[f, 1, 1] * y + R[f, 1, 2] * z + T[f, 1]
            Z = max(R[f, 2, 0] * x + R[f, 2, 1] * y + R[f, 2, 2] * z + T[f, 2], 1e-6)
            du = X / Z - m[f, p, 0]
            dv = Y / Z - m[f, p, 1]
            out[f, p] = w0[f, p] / (1.0 + (du * du + dv * dv) / (robust * robust))
    return out


@njit(cache=True, nogil=True)
def height_terms(rays: np.ndarray, R: np.ndarray, T: np.ndarray, rest: np.ndarray,
                 w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``planar_pinhole._height_terms``: (gg, ga) (F, P) of the algebraic error
    |m x (A + h n)|^2 = gg h^2 + 2 ga h + const, A the rest point posed, n the normal."""
    F, P = w.shape
    gg = np.empty((F, P))
    ga = np.empty((F, P))
    for f in range(F):
        n0, n1, n2 = R[f, 0, 2], R[f, 1, 2], R[f, 2, 2]
        for p in range(P):
            x, y = rest[p, 0], rest[p, 1]
            a0 = R[f, 0, 0] * x + R[f, 0, 1] * y + T[f, 0]
            a1 = R[f, 1, 0] * x + R[f, 1, 1] * y + T[f, 1]
            a2 = R[f, 2, 0] * x + R[f, 2, 1] * y + T[f, 2]
            r0, r1, r2 = rays[f, p, 0], rays[f, p, 1], rays[f, p, 2]
            mm = r0 * r0 + r1 * r1 + r2 * r2
            mn = r0 * n0 + r1 * n1 + r2 * n2
            gg[f, p] = (mm - mn * mn) * w[f, p]
            ga[f, p] = (mm * (a0 * n0 + a1 * n1 + a2 * n2)
                        - mn * (r0 * a0 + r1 * a1 + r2 * a2)) * w[f, p]
    return gg, ga


@njit(cache=True, nogil=True)
def rest_coordinates(rays: np.ndarray, R: np.ndarray, T: np.ndarray, h: np.ndarray,
                     w: np.ndarray, rest: np.ndarray) -> np.ndarray:
    """``planar_pinhole._solve_rest``: per point the rest coordinates (x, y) minimising the
    algebraic error over the frames, the heights h (F, P) given (a 2 x 2 system; a point
    whose system is singular keeps ``rest``)."""
    F, P = w.shape
    a11 = np.zeros(P)
    a22 = np.zeros(P)
    a12 = np.zeros(P)
    b1 = np.zeros(P)
    b2 = np.zeros(P)
    for f in range(F):
        e10, e11, e12 = R[f, 0, 0], R[f, 1, 0], R[f, 2, 0]        # the plane's axes
        e20, e21, e22 = R[f, 0, 1], R[f, 1, 1], R[f, 2, 1]
        n0, n1, n2 = R[f, 0, 2], R[f, 1, 2], R[f, 2, 2]
        e1e2 = e10 * e20 + e11 * e21 + e12 * e22
        for p in range(P):
            wp = w[f, p]
            r0, r1, r2 = rays[f, p, 0], rays[f, p, 1], rays[f, p, 2]
            mm = r0 * r0 + r1 * r1 + r2 * r2
            me1 = r0 * e10 + r1 * e11 + r2 * e12
            me2 = r0 * e20 + r1 * e21 + r2 * e22
            hp = h[f, p]
            c0, c1, c2 = hp * n0 + T[f, 0], hp * n1 + T[f, 1], hp * n2 + T[f, 2]
            mc = r0 * c0 + r1 * c1 + r2 * c2
            ec1 = c0 * e10 + c1 * e11 + c2 * e12
            ec2 = c0 * e20 + c1 * e21 + c2 * e22
            a11[p] += wp * (mm - me1 * me1)
            a22[p] += wp * (mm - me2 * me2)
            a12[p] += wp * (mm * e1e2 - me1 * me2)
            b1[p] -= wp * (mm * ec1 - me1 * mc)
            b2[p] -= wp * (mm * ec2 - me2 * mc)
    out = rest.copy()
    for p in range(P):
        det = a11[p] * a22[p] - a12[p] ** 2
        if det > 1e-12 * max(a11[p] * a22[p], 1e-300):
            out[p, 0] = (a22[p] * b1[p] - a12[p] * b2[p]) / det
            out[p, 1] = (a11[p] * b2[p] - a12[p] * b1[p]) / det
    return out


@njit(cache=True, nogil=True)
def posed_residuals(O: np.ndarray, R: np.ndarray, T: np.ndarray, m: np.ndarray,
                    v: np.ndarray, focal: float) -> np.ndarray:
    """``dspr._pinhole_residual``: (K,) the v-weighted RMS pixel error of each state O[k]
    (P, 3) posed by R[k], T[k] against the normalised points m (P, 2); inf where a point of
    the state is not in front of the camera."""
    K, P, _ = O.shape
    out = np.empty(K)
    vsum = 0.0
    for p in range(P):
        vsum += v[p]
    for k in range(K):
        r00, r01, r02 = R[k, 0, 0], R[k, 0, 1], R[k, 0, 2]
        r10, r11, r12 = R[k, 1, 0], R[k, 1, 1], R[k, 1, 2]
        r20, r21, r22 = R[k, 2, 0], R[k, 2, 1], R[k, 2, 2]
        acc = 0.0
        front = True
        for p in range(P):
            o0, o1, o2 = O[k, p, 0], O[k, p, 1], O[k, p, 2]
            z = r20 * o0 + r21 * o1 + r22 * o2 + T[k, 2]
            if not z > 0.0:
                front = False
                break
            du = (r00 * o0 + r01 * o1 + r02 * o2 + T[k, 0]) / z - m[p, 0]
            dv = (r10 * o0 + r11 * o1 + r12 * o2 + T[k, 1]) / z - m[p, 1]
            acc += (du * du + dv * dv) * focal ** 2 * v[p]
        out[k] = np.sqrt(acc / vsum) if front else np.inf
    return out


@njit(cache=True, nogil=True)
def orthonormal_rows_fit(B: np.ndarray, C: np.ndarray, lam: np.ndarray, R2: np.ndarray,
                         iterations: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``dspr._fit``'s majorisation steps for every state k at once: from camera rows R2
    (K, 2, 3), ``iterations`` times R2 <- polar(s B + s^2 R2 (lam I - C)) with the optimal
    scale s = tr(R2 B^T) / tr(R2 C R2^T), the moments B (K, 2, 3), C (K, 3, 3) and C's
    largest eigenvalue lam (K,) given.  Returns (R2, s, tr(R2 B^T))."""
    K = B.shape[0]
    R2 = R2.copy()
    s = np.empty(K)
    num = np.empty(K)
    M = np.empty((2, 3))
    for k in range(K):
        for it in range(iterations + 1):
            n = 0.0
            d = 0.0
            for i in range(2):
                for a in range(3):
                    n += R2[k, i, a] * B[k, i, a]
                    for b in range(3):
                        d += R2[k, i, a] * C[k, a, b] * R2[k, i, b]
            s[k] = n / max(d, 1e-300)
            num[k] = n
            if it == iterations:
                break
            sk = s[k]
            for i in range(2):
                for b in range(3):
                    acc = 0.0
                    for a in range(3):
                        acc += R2[k, i, a] * ((lam[k] if a == b else 0.0) - C[k, a, b])
                    M[i, b] = sk * B[k, i, b] + sk * sk * acc
            U, _, Vt = np.linalg.svd(M, full_matrices=False)
            R2[k] = U @ Vt
    return R2, s, num


@njit(cache=True, nogil=True)
def bundle_residuals(fi: np.ndarray, pi: np.ndarray, uv: np.ndarray, R: np.ndarray,
                     T: np.ndarray, X: np.ndarray, focal: float, c: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``rigid_pinhole.fit_rigid_pinhole``'s residuals: for observations k of point pi[k] in
    frame fi[k], ``RX`` = R_f X_p, ``Y`` = RX + T_f (camera frame) and ``r`` (n, 2) =
    focal Y_xy / max(Y_z, 1e-9) + c - uv_k px."""
    n = fi.size
    r = np.empty((n, 2))
    Y = np.empty((n, 3))
    RX = np.empty((n, 3))
    for k in range(n):
        f, p = fi[k], pi[k]
        for i in range(3):
            v = R[f, i, 0] * X[p, 0] + R[f, i, 1] * X[p, 1] + R[f, i, 2] * X[p, 2]
            RX[k, i] = v
            Y[k, i] = v + T[f, i]
        z = max(Y[k, 2], 1e-9)
        r[k, 0] = focal * Y[k, 0] / z + c[0] - uv[k, 0]
        r[k, 1] = focal * Y[k, 1] / z + c[1] - uv[k, 1]
    return r, Y, RX


@njit(cache=True, nogil=True)
def bundle_normal_equations(fi: np.ndarray, pi: np.ndarray, r: np.ndarray, Y: np.ndarray,
                            RX: np.ndarray, R: np.ndarray, focal: float, scale2: float,
                            E: np.ndarray) -> tuple[np.ndarray, ...]:
    """``rigid_pinhole.fit_rigid_pinhole``'s normal equations, soft-L1 weighted (IRLS weight
    1 / sqrt(1 + |r|^2 / scale2)): per frame the pose block A (F, 6, 6) and gradient gc (F,
    6) (a left rotation vector, then the translation), per point B (P, 3, 3) and gx (P, 3),
    per observation the pose-point block C (n, 6, 3), also written to E[f, :, p] (E: (F, 6,
    P, 3), the rows of the Schur complement's product)."""
    F, P = E.shape[0], E.shape[2]
    n = fi.size
    A = np.zeros((F, 6, 6))
    B = np.zeros((P, 3, 3))
    gc = np.zeros((F, 6))
    gx = np.zeros((P, 3))
    C = np.empty((n, 6, 3))
    jc = np.empty((2, 6))
    jx = np.empty((2, 3))
    for k in range(n):
        f, p = fi[k], pi[k]
        z = max(Y[k, 2], 1e-9)
        a = focal / z
        x0, x1, x2 = RX[k, 0], RX[k, 1], RX[k, 2]
        for row in range(2):
            j0 = a if row == 0 else 0.0
            j1 = a if row == 1 else 0.0
            j2 = -focal * Y[k, row] / (z * z)
            # d(Y)/d(w) for R <- exp([w]x) R is -[R X]x: a row j gives (R X) x j
            jc[row, 0] = x1 * j2 - x2 * j1
            jc[row, 1] = x2 * j0 - x0 * j2
            jc[row, 2] = x0 * j1 - x1 * j0
            jc[row, 3], jc[row, 4], jc[row, 5] = j0, j1, j2
            for i in range(3):
                jx[row, i] = j0 * R[f, 0, i] + j1 * R[f, 1, i] + j2 * R[f, 2, i]
        w = 1.0 / np.sqrt(1.0 + (r[k, 0] * r[k, 0] + r[k, 1] * r[k, 1]) / scale2)
        for i in range(6):
            wi0, wi1 = w * jc[0, i], w * jc[1, i]
            gc[f, i] += wi0 * r[k, 0] + wi1 * r[k, 1]
            for j in range(6):
                A[f, i, j] += wi0 * jc[0, j] + wi1 * jc[1, j]
            for j in range(3):
                v = wi0 * jx[0, j] + wi1 * jx[1, j]
                C[k, i, j] = v
                E[f, i, p, j] = v
        for i in range(3):
            wi0, wi1 = w * jx[0, i], w * jx[1, i]
            gx[p, i] += wi0 * r[k, 0] + wi1 * r[k, 1]
            for j in range(3):
                B[p, i, j] += wi0 * jx[0, j] + wi1 * jx[1, j]
    return A, B, gc, gx, C


@njit(cache=True, nogil=True)
def bundle_schur_rows(E: np.ndarray, Binv: np.ndarray) -> np.ndarray:
    """E (F, 6, P, 3) with each point's 3x3 block multiplied by Binv[p]: (6F, 3P), the left
    factor of the Schur complement's product E B^-1 E^T."""
    F, P = E.shape[0], E.shape[2]
    out = np.empty((6 * F, 3 * P))
    for f in range(F):
        for i in range(6):
            k = 6 * f + i
            for p in range(P):
                e0, e1, e2 = E[f, i, p, 0], E[f, i, p, 1], E[f, i, p, 2]
                for j in range(3):
                    out[k, 3 * p + j] = e0 * Binv[p, 0, j] + e1 * Binv[p, 1, j] + \
                        e2 * Binv[p, 2, j]
    return out


@njit(cache=True, nogil=True)
def bundle_point_gradient(fi: np.ndarray, pi: np.ndarray, C: np.ndarray, dc: np.ndarray,
                          gx: np.ndarray) -> np.ndarray:
    """gx (P, 3) plus each point's sum of C_k^T dc[fi[k]] over its observations k."""
    out = gx.copy()
    for k in range(fi.size):
        f, p = fi[k], pi[k]
        for j in range(3):
            acc = 0.0
            for i in range(6):
                acc += C[k, i, j] * dc[f, i]
            out[p, j] += acc
    return out


@njit(cache=True, nogil=True)
def weak_image_error(S: np.ndarray, scale: np.ndarray, t: np.ndarray, W: np.ndarray,
                     V: np.ndarray, cx: float, cy: float, ratio: np.ndarray,
                     ratio_scalar: float) -> float:
    """``perspective.perspective_error`` in one pass: the V-weighted mean pixel distance
    between W (2F, P) and the shapes S (F, P, 3) imaged weak-perspective (``scale``, ``t``)
    and divided about (cx, cy) by the depth ratio (``ratio`` (F, P), or ``ratio_scalar``
    where ``ratio`` is empty)."""
    F, P = V.shape
    per_point = ratio.size > 0
    num = 0.0
    den = 0.0
    for f in range(F):
        s, tx, ty = scale[f], t[f, 0], t[f, 1]
        for p in range(P):
            r = ratio[f, p] if per_point else ratio_scalar
            ex = cx + (s * S[f, p, 0] + tx - cx) / r - W[2 * f, p]
            ey = cy + (s * S[f, p, 1] + ty - cy) / r - W[2 * f + 1, p]
            num += np.sqrt(ex * ex + ey * ey) * V[f, p]
            den += V[f, p]
    return num / max(den, 1e-12)
