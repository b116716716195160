"""Synthetic data with known answers for the core tests."""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def low_rank_sequence(K: int = 3, F: int = 60, P: int = 300, seed: int = 0
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Orthographic tracks W (2F, P) of a rank-K shape sequence seen by a rotating camera;
    returns W, camera-frame shapes S (F, P, 3) and rotations R (F, 3, 3)."""
    rng = np.random.default_rng(seed)
    B = rng.normal(size=(K, 3, P))
    B[0] *= 3
    tt = np.linspace(0, 6, F)[:, None]
    c = np.concatenate([np.ones((F, 1)), 0.3 * np.sin(tt * rng.uniform(0.5, 2, (1, K - 1)))],
                       axis=1)
    S_obj = np.einsum('fk,kip->fip', c, B)
    ang = np.stack([0.5 * np.sin(np.linspace(0, 3, F)), 0.8 * np.cos(np.linspace(0, 2, F)),
                    np.linspace(0, 1, F)], axis=1)
    R = Rotation.from_euler('xyz', ang).as_matrix()
    S = np.einsum('fij,fjp->fpi', R, S_obj)
    W = S[:, :, :2].transpose(0, 2, 1).reshape(2 * F, P) + 5.0
    return W, S, R


def reflected_frames_of_a_periodic_flag(mode: str, frames: int = 90, batch: int = 30
                                        ) -> list[bool]:
    """The stream in ``mode`` with the camera, on the ground-truth tracks of a rendered
    periodic flag (128x96, 30 deg sweep, the deformation repeating every 20 frames): for each
    published frame (all of them, in order), whether its depths run against the truth's (the
    centred depths anti-correlated on the shared tracks)."""
    from nrsfm_ros.core.nrsfm.stream import StreamNRSfM
    from nrsfm_ros.io.synth import SynthConfig, generate
    seq = generate(SynthConfig(surface='flag', width=128, height=96, frames=frames,
                               camera_motion_deg=30, period_frames=20, stride=3))
    s = StreamNRSfM(mode=mode, batch_frames=batch, projection='perspective')
    s.set_intrinsics(float(seq.K[0, 0]), seq.K[:2, 2])
    out = []
    for f in range(frames):
        out += s.push(seq.track_ids, seq.W[2 * f:2 * f + 2].T, seq.V[f])
    out += s.flush()
    assert [sh.index for sh in out] == list(range(frames))
    col = {int(i): k for k, i in enumerate(seq.track_ids)}
    reflected = []
    for sh in out:
        g = seq.S[sh.index][[col[int(i)] for i in sh.ids], 2]
        reflected.append(float((sh.X[:, 2] - sh.X[:, 2].mean()) @ (g - g.mean())) < 0)
    return reflected


def bench_module(monkeypatch, name: str):
    """A script of ``bench/`` imported as a module (its folder on sys.path for this test; the
    caller pops it from sys.modules after)."""
    import importlib
    from pathlib import Path
    monkeypatch.syspath_prepend(str(Path(__file__).resolve().parent.parent / 'bench'))
    return importlib.import_module(name)


def quarters(F: int, P: int) -> np.ndarray:
    """Visibility (F, P) of a fragmented batch: tracks q::4 seen in quarter q of the F frames,
    the quarters overlapping by a frame."""
    V = np.zeros((F, P))
    q4 = F // 4
    for q in range(4):
        V[max(0, q4 * q - 1):q4 * q + q4 + 1, q::4] = 1.0
    return V
