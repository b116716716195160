"""The HDM-Net verbs of the CLI: ``train-hdmnet`` (PyTorch, the extra ``learning``) and
``reconstruct-image`` (ONNX Runtime, the default install)."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np


class ToolError(ValueError):
    """Bad input to an HDM-Net verb (the CLI prints one ``error:`` line)."""


def add_train_args(p: argparse.ArgumentParser) -> None:
    p.add_argument('--out', required=True, help='folder for hdmnet.onnx and hdmnet.json')
    p.add_argument('--seed', type=int, default=0, help='data and weight seed (default 0)')
    p.add_argument('--states', type=int, default=None,
                   help='training samples, one deformation state each (default 4000)')
    p.add_argument('--test-states', type=int, default=None,
                   help='samples per test split (default 300)')
    p.add_argument('--epochs', type=int, default=None, help='epochs (default 20)')
    p.add_argument('--batch', type=int, default=None, help='batch size (default 32)')
    p.add_argument('--lr', type=float, default=None, help='peak learning rate (default 2e-3)')
    p.add_argument('--width', type=int, default=None,
                   help='channels of the first encoder stage (default 24)')
    p.add_argument('--pool', type=int, default=None,
                   help='average pooling of the stored 112 px images before the network '
                   '(default 2: a 56 px network; 1: 112 px, ~4x the compute)')
    p.add_argument('--w-align', type=float, default=None,
                   help='weight of the metric-B loss (per-sample Procrustes + scale; default 0)')
    p.add_argument('--w-iso', type=float, default=None,
                   help='weight of the isometry (smoothness) loss (default 1)')
    p.add_argument('--w-contour', type=float, default=None,
                   help='weight of the contour (silhouette) loss (default 1e-3)')
    p.add_argument('--augment', action='store_true', default=None,
                   help='mirror left-right and permute / scale colours during training')
    p.add_argument('--wave-fraction', type=float, default=None,
                   help='share of wave (flag) states among the training states, the rest bent '
                   'sheets (default 0.5; the test splits keep 0.5)')
    p.add_argument('--max-yaw', type=float, default=None,
                   help='camera yaw range of the training states, +-degrees (0..60; default '
                   '35; the test splits keep 35)')
    p.add_argument('--threads', type=int, default=None, help='PyTorch threads (default 2)')
    p.add_argument('--max-steps', type=int, default=None,
                   help='stop after this many optimiser steps (default 0: all epochs)')
    p.add_argument('--init', default=None,
                   help='warm start from the hdmnet.pt of an earlier run or an exported '
                   'hdmnet.onnx (same width; BatchNorm then frozen); the hdmnet.json beside it '
                   'is kept in the new record')


def train_command(args: argparse.Namespace, argv: list[str]) -> int:
    try:
        from .learning import hdmnet_train as T
    except ImportError as err:
        raise ToolError(f'train-hdmnet needs PyTorch (pip install .[learning]): {err}') from err
    cfg = T.main_config(seed=args.seed, states=args.states, test_states=args.test_states,
                        epochs=args.epochs, batch=args.batch, lr=args.lr, width=args.width,
                        threads=args.threads, max_steps=args.max_steps, init=args.init,
                        w_align=args.w_align, w_iso=args.w_iso, w_contour=args.w_contour,
                        augment=args.augment, wave_fraction=args.wave_fraction,
                        pool=args.pool, max_yaw_deg=args.max_yaw)
    meta = T.train(cfg, args.out, command=['nrsfm-ros', *argv],
                   log=lambda s: print(s, flush=True))
    m = meta['metrics']
    print(f"wrote {Path(args.out) / 'hdmnet.onnx'} ({meta['bytes'] / 1e6:.1f} MB) and "
          f"hdmnet.json: e3D test {m['test']['e3d']:.4f}, held-out textures "
          f"{m['heldout-texture']['e3d']:.4f}, held-out lights {m['heldout-light']['e3d']:.4f}")
    return 0


def add_image_args(p: argparse.ArgumentParser) -> None:
    p.add_argument('image', help='image file (png, jpg, ...; read as RGB)')
    p.add_argument('--out', required=True, help='output .npz')
    p.add_argument('--model', default=None,
                   help='ONNX model (default: the shipped nrsfm_ros/models/hdmnet.onnx)')
    p.add_argument('--fx', type=float, default=None,
                   help='focal length (px) of the camera, principal point at the image centre '
                   '(default: the training camera\'s field of view)')


def reconstruct_image_command(args: argparse.Namespace) -> int:
    import cv2

    from .core import hdmnet as H
    from .core.depth import depth_image
    from .io.hdmnet_model import HDMNetModel
    path = Path(args.image)
    if not path.exists():
        raise FileNotFoundError(f'{path} does not exist')
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise ToolError(f'{path}: not an image OpenCV can read')
    rgb = np.ascontiguousarray(bgr[..., ::-1])
    h, w = rgb.shape[:2]
    K = None
    if args.fx is not None:
        if not args.fx > 0:
            raise ToolError(f'--fx {args.fx}: expected > 0')
        K = np.array([[args.fx, 0, (w - 1) / 2], [0, args.fx, (h - 1) / 2], [0, 0, 1.0]])
    model = HDMNetModel(args.model)
    res = model.predict(rgb, K)
    Kd = model.last_K
    depth = depth_image(H.grid_uv(res.points, Kd).reshape(-1, 2), res.points[..., 2].ravel(),
                        (h, w))
    np.savez_compressed(args.out, points=res.points.astype(np.float32), valid=res.valid,
                        depth=depth, K=Kd, infer_ms=res.infer_ms)
    print(f'wrote {args.out}: points {res.points.shape} ({int(res.valid.sum())} valid), depth '
          f'{h}x{w}, {res.infer_ms:.1f} ms inference', file=sys.stdout)
    return 0
