"""Study (issue 12, not used by the product yet): a perspective refinement of the ``planar``
model against the stream's perspective step, on ground-truth tracks of ``synth`` renders.

    .venv/bin/python bench/study_planar_perspective.py [--cases flag:30:1:1.6,sheet:30:1:1.6]
        [--rounds 12] [--rank 2] [--json out.json]

Case = surface:camera motion (deg):amplitude:distance (m; 1.6 = a ~45 deg field of view, 4 the
sweep's ~19 deg).  Columns (metric B, per-frame Procrustes + scale, as bench_pipeline.py):
``persp step`` = ``perspective.perspective_solve`` of ``planar`` (what the stream publishes for a
planar batch with CameraInfo); ``refined`` = that result refined under the pinhole camera:

- model: object-frame points ``(x_p, y_p, h_fp)`` (rest coordinates + heights), camera poses
  ``(R_f, T_f)``, heights of rank ``--rank`` over the frames, ``h = C B``;
- per round: each frame's pose by 3 Gauss-Newton steps on the pinhole reprojection error; then
  C (F, K) and B (K, P) by 3 alternations of linear least squares on the algebraic error
  ``m x (R_f (x_p e1 + y_p e2 + h_fp e3) + T_f)`` (m the track's normalised ray); then the rest
  coordinates (2 x 2 per point);
- start: the perspective step's result in the camera frame (depth ``1 + z / f``), the object
  frame from frame 0's principal axes, C and B from the rank-K SVD of the first heights along
  the rays.

``true depths``: the stream on the tracks corrected by the true depths (bench_pipeline's
``--true-depths`` bound).  ``px``: the pinhole reprojection error of each.  The prototype's
pose step is a Python loop over frames (seconds per batch): vectorising it comes before any
use in the stream (BENCHMARKS, "Field of view").
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / 'bench'))

from bench_pipeline import true_depth_bound  # noqa: E402
from benchlib import parser, table  # noqa: E402
from nrsfm_ros.core.nrsfm import reconstruct  # noqa: E402
from nrsfm_ros.core.nrsfm.perspective import perspective_solve  # noqa: E402
from nrsfm_ros.core.registration.rays import _rodrigues, _skew  # noqa: E402
from nrsfm_ros.evaluation import score, shapes_as_clouds  # noqa: E402
from nrsfm_ros.io.synth import SynthConfig, generate  # noqa: E402


def _pose_step(O: np.ndarray, m: np.ndarray, w: np.ndarray, R: np.ndarray, T: np.ndarray,
               steps: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Gauss-Newton on the reprojection error of object points O (P, 3) against normalised
    image points m (P, 2), weights w (P,)."""
    for _ in range(steps):
        RO = O @ R.T
        X = RO + T
        z = X[:, 2]
        r = (X[:, :2] / z[:, None] - m) * w[:, None]
        Jp = np.zeros((z.size, 2, 3))
        Jp[:, 0, 0] = Jp[:, 1, 1] = 1 / z
        Jp[:, 0, 2] = -X[:, 0] / z ** 2
        Jp[:, 1, 2] = -X[:, 1] / z ** 2
        S = -_skew(RO)                        # d(RO)/d(small rotation)
        J = (np.concatenate([Jp @ S, Jp], 2) * w[:, None, None]).reshape(-1, 6)
        d = np.linalg.solve(J.T @ J + 1e-9 * np.eye(6), -J.T @ r.reshape(-1))
        R, T = _rodrigues(d[:3]) @ R, T + d[3:]
    return R, T


def refine(X0: np.ndarray, W: np.ndarray, V: np.ndarray, K: np.ndarray, rounds: int,
           rank: int) -> tuple[np.ndarray, float]:
    """Refined camera-frame points (F, P, 3) from the start X0 (F, P, 3) and the pinhole
    reprojection error (px)."""
    F, P, _ = X0.shape
    rays = np.einsum('ij,fjp->fpi', np.linalg.inv(K),
                     np.concatenate([W.reshape(F, 2, P), np.ones((F, 1, P))], 1))
    m, w = rays[..., :2], (V >= 0.5).astype(float)
    T = X0.mean(1)
    C0 = X0 - T[:, None]
    axes = np.linalg.svd(C0[0] - C0[0].mean(0), full_matrices=False)[2]
    if np.linalg.det(axes) < 0:
        axes[2] *= -1
    R = np.empty((F, 3, 3))
    for f in range(F):
        u, _, vt = np.linalg.svd(C0[f].T @ C0[0])
        R[f] = u @ np.diag([1, 1, np.sign(np.linalg.det(u @ vt))]) @ vt @ axes.T
    O = np.einsum('fji,fpj->fpi', R, C0)
    rest, h = O[:, :, :2].mean(0), O[:, :, 2]
    Cf = Bp = None
    for rnd in range(rounds):
        pts = np.concatenate([np.broadcast_to(rest, (F, P, 2)), h[..., None]], 2)
        for f in range(F):
            R[f], T[f] = _pose_step(pts[f], m[f], w[f], R[f], T[f])
        A = np.einsum('fij,fpj->fpi', R[:, :, :2], np.broadcast_to(rest, (F, P, 2))) + T[:, None]
        n = np.broadcast_to(R[:, None, :, 2], A.shape)
        cA, cn = np.cross(rays, A), np.cross(rays, n)
        gg, ga = (cn * cn).sum(2) * w, (cn * cA).sum(2) * w
        if Cf is None:
            U, s, Vt = np.linalg.svd(-ga / np.maximum(gg, 1e-15), full_matrices=False)
            Cf, Bp = U[:, :rank] * s[:rank], Vt[:rank].copy()
        eye = 1e-12 * np.eye(rank)
        for _ in range(3):
            Cf = np.linalg.solve(np.einsum('fp,kp,lp->fkl', gg, Bp, Bp) + eye,
                                 -np.einsum('fp,kp->fk', ga, Bp)[..., None])[..., 0]
            Bp = np.linalg.solve(np.einsum('fp,fk,fl->pkl', gg, Cf, Cf) + eye,
                                 -np.einsum('fp,fk->pk', ga, Cf)[..., None])[..., 0].T
        h = Cf @ Bp
        e1 = np.broadcast_to(R[:, None, :, 0], A.shape)
        e2 = np.broadcast_to(R[:, None, :, 1], A.shape)
        c1, c2 = np.cross(rays, e1), np.cross(rays, e2)
        c0 = np.cross(rays, h[..., None] * n + T[:, None])
        ww = w[..., None]
        a11, a12 = (ww * c1 * c1).sum((0, 2)), (ww * c1 * c2).sum((0, 2))
        a22 = (ww * c2 * c2).sum((0, 2))
        b1, b2 = -(ww * c1 * c0).sum((0, 2)), -(ww * c2 * c0).sum((0, 2))
        det = a11 * a22 - a12 ** 2
        ok = det > 1e-18
        rest[ok, 0] = (a22 * b1 - a12 * b2)[ok] / det[ok]
        rest[ok, 1] = (a11 * b2 - a12 * b1)[ok] / det[ok]
    pts = np.concatenate([np.broadcast_to(rest, (F, P, 2)), h[..., None]], 2)
    X = np.einsum('fij,fpj->fpi', R, pts) + T[:, None]
    err = np.linalg.norm(X[..., :2] / X[..., 2:3] - m, axis=2)
    return X, float((err * w).sum() / w.sum()) * float(K[0, 0])


def run_case(case: str, rounds: int, rank: int, size: tuple[int, int] = (256, 192),
             frames: int = 60) -> dict:
    surface, motion, amp, dist = case.split(':')
    seq = generate(SynthConfig(surface=surface, width=size[0], height=size[1], frames=frames,
                               seed=0,
                               camera_motion_deg=float(motion), amplitude=float(amp),
                               distance=float(dist)))
    V = np.maximum(seq.V, 1e-3)
    f, c = float(seq.K[0, 0]), seq.K[:2, 2]

    def e3d(S: np.ndarray) -> float:
        return score(shapes_as_clouds(S, seq.track_ids), seq).summary()['e3d']

    def solve(W: np.ndarray, V: np.ndarray):
        return reconstruct(W, V, method='planar')
    step = perspective_solve(solve, seq.W, V, f, c, weak=solve(seq.W, V))
    X = step.S * step.scale[:, None, None]
    X0 = np.stack([(X[..., 0] + step.t[:, None, 0] - c[0]) / f,
                   (X[..., 1] + step.t[:, None, 1] - c[1]) / f, 1 + X[..., 2] / f], 2)
    t = time.perf_counter()
    Xr, px = refine(X0, seq.W, seq.V, seq.K, rounds, rank)
    return {'case': case, 'static': score(shapes_as_clouds(seq.S, seq.track_ids),
                                           seq).summary()['static'],
            'step': e3d(step.S), 'step_px': step.residual_px, 'refined': e3d(Xr),
            'refined_px': px, 'refine_s': time.perf_counter() - t,
            'true_depths': true_depth_bound(seq)}


def main() -> None:
    p = parser(__doc__)
    p.add_argument('--cases', default='flag:30:1:1.6,sheet:30:1:1.6')
    p.add_argument('--rounds', type=int, default=12)
    p.add_argument('--rank', type=int, default=2)
    a = p.parse_args()
    rows = [run_case(case, a.rounds, a.rank) for case in a.cases.split(',')]
    table(['case (surface:deg:amp:m)', 'static', 'persp step', 'px', 'refined', 'px',
           'refined / step', 'true depths', 'refine s'],
          [[r['case'], f"{r['static']:.4f}", f"{r['step']:.4f}", f"{r['step_px']:.3f}",
            f"{r['refined']:.4f}", f"{r['refined_px']:.3f}", f"{r['refined'] / r['step']:.2f}",
            f"{r['true_depths']:.4f}", f"{r['refine_s']:.1f}"] for r in rows])
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1))


if __name__ == '__main__':
    main()
