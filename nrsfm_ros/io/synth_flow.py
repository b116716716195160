"""Dense ground-truth scene flow of a synthetic sequence (:mod:`nrsfm_ros.io.synth`), in the
definition of :mod:`nrsfm_ros.core.sceneflow.definition`, from the renderer's public outputs.

The renderer's ground-truth tracks are the surface points seen at frame 0's pixels (every
``stride``-th one; ``SynthConfig(stride=1)`` for a dense field), with their camera-frame
positions ``S`` and world positions ``S_world`` in every frame.  Flow images are indexed by
those frame-0 pixels; a pixel is valid where the surface (not the background, not the
occluder) is visible in frame 0.
"""
from __future__ import annotations

import numpy as np

from ..core.sceneflow.definition import FRAMES
from .synth import SynthSequence


def dense_scene_flow(seq: SynthSequence, frame: str = 'camera', pairs: str = 'reference'
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Ground-truth flow (F-1, H, W, 3) float32 metres (NaN where no track) and valid (H, W).

    ``pairs='reference'``: frame 0 -> frame f (f = 1..F-1), what MSF and ``nrsfm-ros
    scene-flow`` estimate; ``'consecutive'``: frame f-1 -> frame f of the same surface points.
    ``frame='camera'``: X_b - X_a (camera coordinates, ego-motion included); ``'object'``: the
    ego-motion removed, in camera a's optical frame (``R_a (X_world_b - X_world_a)``)."""
    if frame not in FRAMES:
        raise ValueError(f'frame={frame!r}: expected one of {FRAMES}')
    if pairs not in ('reference', 'consecutive'):
        raise ValueError(f"pairs={pairs!r}: expected 'reference' or 'consecutive'")
    F = seq.S.shape[0]
    H, W = seq.depth.shape[1:]
    a = np.zeros(F - 1, int) if pairs == 'reference' else np.arange(F - 1)
    b = np.arange(1, F)
    if frame == 'camera':
        d = seq.S[b] - seq.S[a]
    else:
        R = seq.T_camera_world[a, :3, :3]
        d = np.einsum('fij,fpj->fpi', R, seq.S_world[b] - seq.S_world[a])
    flow = np.full((F - 1, H * W, 3), np.nan, np.float32)
    flow[:, seq.track_ids.astype(np.int64)] = d
    valid = np.zeros(H * W, bool)
    valid[seq.track_ids.astype(np.int64)] = seq.V[0] > 0
    return flow.reshape(F - 1, H, W, 3), valid.reshape(H, W)
