"""The pinhole fits' per-frame kernels (core/nrsfm/_pinhole_kernels.py) against the same sums
written as NumPy array expressions (the implementations they replaced)."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from nrsfm_ros.core.nrsfm.perspective import RATIO_RANGE, frame_errors, reflect_frames
from nrsfm_ros.core.nrsfm.planar_pinhole import pose_steps
from nrsfm_ros.core.nrsfm.result import NRSfMResult


def numpy_pose_steps(O, m, w, R, T, steps):
    F, P = w.shape
    J = np.empty((F, 6, 2, P))
    r = np.empty((F, 2, P))
    for _ in range(steps):
        RO = O @ R.transpose(0, 2, 1)
        a, b, c = RO[..., 0], RO[..., 1], RO[..., 2]
        X, Y, Z = a + T[:, 0, None], b + T[:, 1, None], c + T[:, 2, None]
        front = Z > 1e-6
        iz = np.where(front, 1.0 / np.where(front, Z, 1.0), 0.0)
        ww = w * front
        wz = ww * iz
        gx, gy = -X * iz * wz, -Y * iz * wz
        r[:, 0] = (X * iz - m[..., 0]) * ww
        r[:, 1] = (Y * iz - m[..., 1]) * ww
        J[:, 0, 0], J[:, 1, 0], J[:, 2, 0] = gx * b, wz * c - gx * a, -wz * b
        J[:, 3, 0], J[:, 4, 0], J[:, 5, 0] = wz, 0.0, gx
        J[:, 0, 1], J[:, 1, 1], J[:, 2, 1] = gy * b - wz * c, -gy * a, wz * a
        J[:, 3, 1], J[:, 4, 1], J[:, 5, 1] = 0.0, wz, gy
        Jf = J.reshape(F, 6, 2 * P)
        d = np.linalg.solve(Jf @ Jf.transpose(0, 2, 1) + 1e-12 * np.eye(6),
                            -(Jf @ r.reshape(F, 2 * P, 1)))[..., 0]
        R = Rotation.from_rotvec(d[:, :3]).as_matrix() @ R
        T = T + d[:, 3:]
    return R, T


def numpy_frame_errors(res, W, V, focal, principal):
    F, P = V.shape
    x = res.S[:, :, :2] * res.scale[:, None, None]
    z = res.S[:, :, 2] * res.scale[:, None]
    w = W.reshape(F, 2, P).transpose(0, 2, 1)
    c = principal[None, None, :]
    out = np.empty((F, 2))
    for k, sign in enumerate((1.0, -1.0)):
        a = 1.0 / np.clip(1.0 + sign * z / focal, *RATIO_RANGE)
        r0 = c + (x + res.t[:, None, :] - c) * a[:, :, None] - w
        t = -(V[:, :, None] * a[:, :, None] * r0).sum(1) / \
            np.maximum((V * a * a).sum(1), 1e-12)[:, None]
        e = np.linalg.norm(r0 + t[:, None, :] * a[:, :, None], axis=2)
        out[:, k] = (e * V).sum(1) / np.maximum(V.sum(1), 1e-12)
    return out


def test_pose_steps_equal_the_array_form_and_recover_the_poses():
    rng = np.random.default_rng(0)
    F, P = 7, 300
    O = rng.standard_normal((F, P, 3)) * 0.2
    R = Rotation.random(F, random_state=1).as_matrix()
    T = np.array([0.0, 0.0, 3.0]) + rng.standard_normal((F, 3)) * 0.05
    X = O @ R.transpose(0, 2, 1) + T[:, None]
    m = X[..., :2] / X[..., 2:3]
    w = (rng.random((F, P)) > 0.2) * rng.uniform(0.5, 1.0, (F, P))
    O[0, :5, 2] = -10.0                 # points behind the camera in frame 0 count nothing
    R0 = Rotation.from_rotvec(rng.standard_normal((F, 3)) * 0.05).as_matrix() @ R
    T0 = T + rng.standard_normal((F, 3)) * 0.02
    Ra, Ta = pose_steps(O, m, w, R0, T0, 3)
    Rb, Tb = numpy_pose_steps(O, m, w, R0, T0, 3)
    np.testing.assert_allclose(Ra, Rb, atol=1e-12)
    np.testing.assert_allclose(Ta, Tb, atol=1e-12)
    assert np.abs(Ra[1:] - R[1:]).max() < 1e-6 and np.abs(Ta[1:] - T[1:]).max() < 1e-6
    assert np.abs(R0 - R).max() > 1e-2          # the start was off


def test_frame_errors_equal_the_array_form():
    rng = np.random.default_rng(1)
    F, P, focal, principal = 6, 400, 250.0, np.array([128.0, 96.0])
    S = rng.standard_normal((F, P, 3)) * 40.0
    S[2, :10, 2] = 1e4                  # depth ratios past both ends of RATIO_RANGE
    S[3, :10, 2] = -1e4
    res = NRSfMResult(S=S, R=np.tile(np.eye(3), (F, 1, 1)), scale=rng.uniform(0.8, 1.2, F),
                      t=principal + rng.standard_normal((F, 2)), method='x', rank=0,
                      residual_px=0.0, iterations=0, converged=True, seconds=0.0)
    W = rng.standard_normal((2 * F, P)) * 30.0 + 100.0
    V = (rng.random((F, P)) > 0.3).astype(float)
    V[5] = 0.0                          # a frame with nothing visible: zeros, no NaN
    got = frame_errors(res, W, V, focal, principal)
    np.testing.assert_allclose(got, numpy_frame_errors(res, W, V, focal, principal),
                               rtol=1e-12, atol=1e-12)
    assert np.isfinite(got).all() and (got[5] == 0).all()
    flipped = frame_errors(reflect_frames(res, -np.ones(F)), W, V, focal, principal)
    np.testing.assert_allclose(flipped, got[:, ::-1], rtol=1e-12)


def numpy_reprojection(X, m, w, robust=0.0):
    z = X[..., 2:3]
    if not (z > 0).all():
        return np.inf
    e = np.linalg.norm(X[..., :2] / z - m, axis=2)
    if robust > 0:
        e = robust * np.log1p((e / robust) ** 2)
    return float((e * w).sum() / max(w.sum(), 1e-12))


def numpy_cauchy(pts, R, T, m, w0, robust):
    X = pts @ R.transpose(0, 2, 1) + T[:, None]
    e = np.linalg.norm(X[..., :2] / np.maximum(X[..., 2:3], 1e-6) - m, axis=2)
    return w0 / (1.0 + (e / robust) ** 2)


def numpy_height_terms(rays, R, T, rest, w):
    A = rest @ R[:, :, :2].transpose(0, 2, 1) + T[:, None]
    n = R[:, :, 2]
    mm = (rays * rays).sum(2)
    mn = rays @ n[:, :, None]
    gg = mm - mn[..., 0] ** 2
    ga = mm * (A @ n[:, :, None])[..., 0] - mn[..., 0] * (rays * A).sum(2)
    return gg * w, ga * w


def numpy_solve_rest(rays, R, T, h, w, rest):
    mm = (rays * rays).sum(2)
    me = rays @ R[:, :, :2]
    c = h[..., None] * R[:, None, :, 2] + T[:, None]
    mc = (rays * c).sum(2)
    e1e2 = (R[:, :, 0] * R[:, :, 1]).sum(1)[:, None]
    ec = c @ R[:, :, :2]
    a11 = (w * (mm - me[..., 0] ** 2)).sum(0)
    a22 = (w * (mm - me[..., 1] ** 2)).sum(0)
    a12 = (w * (mm * e1e2 - me[..., 0] * me[..., 1])).sum(0)
    b1 = -(w * (mm * ec[..., 0] - me[..., 0] * mc)).sum(0)
    b2 = -(w * (mm * ec[..., 1] - me[..., 1] * mc)).sum(0)
    det = a11 * a22 - a12 ** 2
    ok = det > 1e-12 * np.maximum(a11 * a22, 1e-300)
    rest = rest.copy()
    rest[ok, 0] = (a22 * b1 - a12 * b2)[ok] / det[ok]
    rest[ok, 1] = (a11 * b2 - a12 * b1)[ok] / det[ok]
    return rest


def test_planar_round_terms_equal_the_array_form():
    from nrsfm_ros.core.nrsfm import planar_pinhole as pp
    rng = np.random.default_rng(2)
    F, P = 5, 200
    R = Rotation.random(F, random_state=3).as_matrix()
    T = np.array([0.0, 0.0, 2.0]) + rng.standard_normal((F, 3)) * 0.1
    rest = rng.standard_normal((P, 2)) * 0.3
    h = rng.standard_normal((F, P)) * 0.05
    pts = pp._posed(rest, h)
    X = pts @ R.transpose(0, 2, 1) + T[:, None]
    m = X[..., :2] / X[..., 2:3] + rng.standard_normal((F, P, 2)) * 0.01
    rays = np.concatenate([m, np.ones((F, P, 1))], 2)
    w = (rng.random((F, P)) > 0.2) * rng.uniform(0.2, 1.0, (F, P))
    w[:, 0] = 0.0                       # a point never seen keeps its rest coordinates
    for robust in (0.0, 0.02):
        assert np.isclose(pp._reprojection(X, m, w, robust),
                          numpy_reprojection(X, m, w, robust), rtol=1e-12, atol=0)
    behind = X.copy()
    behind[2, 7, 2] = -0.1
    assert pp._reprojection(behind, m, w) == np.inf
    np.testing.assert_allclose(pp._cauchy(rest, h, R, T, m, w, 0.02),
                               numpy_cauchy(pts, R, T, m, w, 0.02), rtol=1e-12, atol=1e-15)
    for got, want in zip(pp._height_terms(rays, R, T, rest, w),
                         numpy_height_terms(rays, R, T, rest, w)):
        np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-13)
    start = rng.standard_normal((P, 2))
    got = pp._solve_rest(rays, R, T, h, w, start)
    np.testing.assert_allclose(got, numpy_solve_rest(rays, R, T, h, w, start), rtol=1e-9,
                               atol=1e-12)
    assert (got[0] == start[0]).all()
    assert np.median(np.abs(got[1:] - rest[1:])) < 0.02      # near the truth despite noise


def test_posed_residuals_equal_the_array_form():
    from nrsfm_ros.core.nrsfm.dspr import _pinhole_residual
    rng = np.random.default_rng(4)
    K, P, focal = 4, 300, 400.0
    O = rng.standard_normal((K, P, 3)) * 0.1
    R = Rotation.random(K, random_state=5).as_matrix()
    T = np.array([0.0, 0.0, 1.5]) + rng.standard_normal((K, 3)) * 0.05
    m = rng.standard_normal((P, 2)) * 0.1
    v = rng.uniform(0.0, 1.0, P)
    T[3, 2] = -1.0                      # the last state behind the camera
    X = O @ R.transpose(0, 2, 1) + T[:, None]
    z = X[..., 2]
    e2 = ((X[..., :2] / np.where(z > 0, z, 1.0)[..., None] - m) ** 2).sum(2) * focal ** 2
    want = np.where((z > 0).all(1), np.sqrt((e2 * v).sum(1) / v.sum()), np.inf)
    got = _pinhole_residual(O, R, T, m, v, focal)
    np.testing.assert_allclose(got[:3], want[:3], rtol=1e-12)
    assert np.isinf(got[3]) and np.isinf(want[3]) and np.isfinite(got[:3]).all()


def test_state_fits_equal_the_array_form():
    """dspr's orthographic fit of every state: the majorisation loop against its NumPy form,
    and the known camera of an exact image recovered."""
    from nrsfm_ros.core.nrsfm.dspr import PROCRUSTES_ITERATIONS, _polar_rows, fit_states
    rng = np.random.default_rng(6)
    K, P = 3, 250
    states = rng.standard_normal((K, P, 3)) * [1.0, 0.8, 0.3]
    R = Rotation.random(random_state=7).as_matrix()[:2]
    uv = 2.0 * states[1] @ R.T + [40.0, -7.0]
    v = rng.uniform(0.3, 1.0, P)
    got = fit_states(states, uv, v)
    Vs = v.sum()
    wc = uv - v @ uv / Vs
    St = states.transpose(0, 2, 1)
    c = (St @ v) / Vs
    B = np.matmul((wc * v[:, None]).T[None], states)
    C = np.matmul(St * v, states) - Vs * c[:, :, None] * c[:, None, :]
    eps = 1e-12 * np.maximum(np.trace(C, axis1=1, axis2=2), 1e-300)
    R2 = _polar_rows(np.linalg.solve(C + eps[:, None, None] * np.eye(3),
                                     B.transpose(0, 2, 1)).transpose(0, 2, 1))

    def scale(R2):
        num = np.einsum('kij,kij->k', R2, B)
        return num / np.einsum('kij,kjl,kil->k', R2, C, R2), num
    s, _ = scale(R2)
    lam = np.linalg.eigvalsh(C)[:, -1]
    for _ in range(PROCRUSTES_ITERATIONS):
        R2 = _polar_rows(s[:, None, None] * B + (s ** 2)[:, None, None]
                         * (R2 @ (lam[:, None, None] * np.eye(3) - C)))
        s, _ = scale(R2)
    flip = np.where(s < 0, -1.0, 1.0)
    np.testing.assert_allclose(got.R2, R2 * flip[:, None, None], atol=1e-10)
    np.testing.assert_allclose(got.scale, np.abs(s), rtol=1e-10)
    np.testing.assert_allclose(got.R2[1], R, atol=1e-8)        # the state that made the image
    assert abs(got.scale[1] - 2.0) < 1e-8 and got.residual_px[1] < 1e-6 < got.residual_px[0]


def test_bundle_kernels_equal_the_array_form():
    """fit_rigid_pinhole's residuals, soft-L1 normal equations, Schur rows and point gradient
    against the NumPy expressions they replaced, on observations with hidden entries."""
    from nrsfm_ros.core.nrsfm._pinhole_kernels import (bundle_normal_equations,
                                                       bundle_point_gradient, bundle_residuals,
                                                       bundle_schur_rows)
    rng = np.random.default_rng(7)
    F, P, focal, s2 = 5, 40, 300.0, 4.0
    c = np.array([160.0, 120.0])
    R = Rotation.random(F, random_state=8).as_matrix()
    T = np.array([0.0, 0.0, 3.0]) + rng.normal(0, 0.1, (F, 3))
    X = rng.normal(0, 0.3, (P, 3))
    fi, pi = np.nonzero(rng.uniform(size=(F, P)) > 0.2)
    uv = rng.uniform(0, 300, (fi.size, 2))
    # residuals
    RX = np.einsum('nij,nj->ni', R[fi], X[pi])
    Y = RX + T[fi]
    r = focal * Y[:, :2] / Y[:, 2:] + c - uv
    got = bundle_residuals(fi, pi, uv, R, T, X, focal, c)
    for a, b in zip(got, (r, Y, RX)):
        np.testing.assert_allclose(a, b, rtol=1e-13, atol=1e-12)
    # normal equations
    z = Y[:, 2]
    Jy = np.zeros((fi.size, 2, 3))
    Jy[:, 0, 0] = Jy[:, 1, 1] = focal / z
    Jy[:, :, 2] = -focal * Y[:, :2] / (z * z)[:, None]
    Jc = np.concatenate([np.cross(RX[:, None, :], Jy), Jy], axis=2)
    Jx = Jy @ R[fi]
    w = 1.0 / np.sqrt(1.0 + (r * r).sum(1) / s2)
    wJc, wJx = Jc * w[:, None, None], Jx * w[:, None, None]
    A = np.zeros((F, 6, 6))
    B = np.zeros((P, 3, 3))
    gc, gx = np.zeros((F, 6)), np.zeros((P, 3))
    np.add.at(A, fi, np.einsum('nki,nkj->nij', wJc, Jc))
    np.add.at(B, pi, np.einsum('nki,nkj->nij', wJx, Jx))
    np.add.at(gc, fi, np.einsum('nki,nk->ni', wJc, r))
    np.add.at(gx, pi, np.einsum('nki,nk->ni', wJx, r))
    C = np.einsum('nki,nkj->nij', wJc, Jx)
    E = np.full((F, 6, P, 3), np.nan)
    E[:] = 0.0
    got = bundle_normal_equations(fi, pi, r, Y, RX, R, focal, s2, E)
    for a, b in zip(got, (A, B, gc, gx, C)):
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-9 * np.abs(b).max())
    Ewant = np.zeros((P, F, 6, 3))
    Ewant[pi, fi] = C
    np.testing.assert_allclose(E, Ewant.transpose(1, 2, 0, 3), rtol=1e-10,
                               atol=1e-9 * np.abs(C).max())
    # the Schur rows E B^-1 and the points' gradient with the poses' step
    Binv = np.linalg.inv(B + np.eye(3))
    want = np.einsum('fipk,pkj->fipj', E, Binv).reshape(6 * F, 3 * P)
    np.testing.assert_allclose(bundle_schur_rows(E, Binv), want, rtol=1e-12,
                               atol=1e-12 * np.abs(want).max())
    dc = rng.normal(size=(F, 6))
    want = gx.copy()
    np.add.at(want, pi, np.einsum('nij,ni->nj', C, dc[fi]))
    np.testing.assert_allclose(bundle_point_gradient(fi, pi, C, dc, gx), want, rtol=1e-12,
                               atol=1e-12 * np.abs(want).max())


def test_perspective_error_equals_the_array_form():
    """perspective_error's one-pass kernel against the array form it replaced, with a depth
    ratio per point and a scalar one."""
    from nrsfm_ros.core.nrsfm.perspective import perspective_error
    rng = np.random.default_rng(9)
    F, P = 6, 200
    res = NRSfMResult(S=rng.normal(size=(F, P, 3)) * 50, R=np.tile(np.eye(3), (F, 1, 1)),
                      scale=rng.uniform(0.8, 1.2, F), t=rng.uniform(100, 200, (F, 2)),
                      method='rigid', rank=1, residual_px=0.0, iterations=1, converged=True,
                      seconds=0.0)
    W = rng.uniform(50, 250, (2 * F, P))
    V = rng.uniform(0, 1, (F, P))
    c = np.array([160.0, 120.0])
    for ratio in (rng.uniform(0.9, 1.1, (F, P)), 1.0, 1.05):
        want = 0.0
        d2 = np.zeros((F, P))
        for k in (0, 1):
            e = c[k] + (res.scale[:, None] * res.S[:, :, k] + res.t[:, k, None] - c[k]) / ratio \
                - W[k::2]
            d2 += e * e
        want = (np.sqrt(d2) * V).sum() / V.sum()
        assert perspective_error(res, W, V, 500.0, c, ratio) == pytest.approx(want, rel=1e-12)
