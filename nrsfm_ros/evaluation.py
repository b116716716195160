"""End-to-end evaluation against a synthetic sequence's ground truth: what a subscriber receives.

Clouds are matched to ground truth by header stamp (frame) and ``track_id`` (point); a frame
without a cloud, or with too few matched points, is listed as unscored, never scored.  Each
score comes with the trivial baselines on the same frames and points (``core.metrics``), and the
rigid factorisation on the ground-truth tracks.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from .core.metrics import StreamScore, score_stream
from .core.nrsfm import reconstruct
from .io import pointcloud2 as pc2
from .io.bag import deserialize, read_messages
from .io.msgtypes import stamp_ns
from .io.synth import SynthSequence
from .params import ReconstructorParams
from .processing import TOPICS, make_stream


def read_clouds(bag: str | Path, stamps_ns: np.ndarray, topic: str = TOPICS['points']
                ) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """``{frame: (X (n, 3), track_id (n,))}`` of the clouds on ``topic`` whose stamps are
    frames of the sequence (``stamps_ns``)."""
    index = {int(s): i for i, s in enumerate(stamps_ns)}
    out: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    for m in read_messages(bag):
        if m.topic.lstrip('/') != topic:
            continue
        msg = deserialize(m.raw, m.msgtype)
        f = index.get(stamp_ns(msg.header))
        if f is not None:
            out[f] = (pc2.read_xyz(msg, skip_nans=False),
                      pc2.read_fields(msg, ('track_id',), np.uint32)[:, 0])
    return out


def shapes_as_clouds(S: np.ndarray, ids: np.ndarray) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """A full reconstruction S (F, P, 3) of the tracks ``ids`` as per-frame clouds."""
    return {f: (S[f], ids) for f in range(S.shape[0])}


def stream_on_tracks(W: np.ndarray, V: np.ndarray, ids: np.ndarray,
                     K: np.ndarray | None = None, **params: Any
                     ) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """The streaming reconstructor (``StreamNRSfM``, reconstructor defaults unless given) fed
    the tracks W (2F, P), V (F, P) frame by frame, with the camera intrinsics ``K`` as from
    CameraInfo (None: none arrived): what it would publish, in image units."""
    stream = make_stream(ReconstructorParams(), **params)
    if K is not None:
        stream.set_intrinsics(float(K[0, 0]), np.asarray(K)[:2, 2])
    out = {}
    F = V.shape[0]
    for f in range(F):
        for sh in stream.push(ids, W[2 * f:2 * f + 2].T, V[f]):
            out[sh.index] = (sh.X, sh.ids)
    for sh in stream.flush():
        out[sh.index] = (sh.X, sh.ids)
    return out


def score(clouds: dict[int, tuple[np.ndarray, np.ndarray]], seq: SynthSequence) -> StreamScore:
    return score_stream(clouds, seq.track_ids, seq.S)


def rigid_on_ground_truth(seq: SynthSequence) -> float:
    """e3D of the rigid factorisation of the ground-truth tracks (a baseline)."""
    res = reconstruct(seq.W, np.maximum(seq.V, 1e-3), method='rigid')
    return score(shapes_as_clouds(res.S, seq.track_ids), seq).summary()['e3d']
