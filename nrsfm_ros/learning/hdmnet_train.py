"""HDM-Net training (PyTorch, the optional extra ``learning``) and ONNX export.

The network (METHODS.md section 8): a residual CNN encoder (stride-2 stages) to a 2 x 2
bottleneck, a fully connected code of ``n_basis`` coefficients, and a linear decoder to the
GRID x GRID x 3 output that starts as the training grids' mean plus their principal modes.
Training sees the data stored at half the input size (``HDMDataConfig.stored``, the
INPUT_SIZE render area-averaged) and pools it by ``pool``; the exported model starts with the
same average pooling, so it takes the INPUT_SIZE image of ``core.hdmnet.preprocess``.

Losses: 3-D (mean squared distance to the ground-truth nodes, plus ``w_shape`` x the same for
the grids centred on their centroids: the shape, which metric B scores), isometry (the grid
against its Gaussian-smoothed self: wrinkles cost) and contour (a soft silhouette of Gaussian
splats of the projected nodes against the rendered mask).
"""
from __future__ import annotations

import hashlib
import json
import subprocess
import sys
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch
import torch.nn.functional as Fn
from torch import nn

from ..core import hdmnet as H
from ..io import synth_hdmnet as D

SIL = 28                    # px: contour loss silhouette resolution
SIL_STEP = 4                # every 3rd grid node is splatted
SIL_SIGMA = 0.7             # px at SIL


@dataclass(frozen=True)
class TrainConfig:
    seed: int = 0
    states: int = 4000          # training samples (one deformation state each)
    test_states: int = 300      # samples per test split
    epochs: int = 20
    batch: int = 32
    lr: float = 2e-3
    width: int = 24             # channels of the first stage (stages: 1, 2, 4, 16/3, 16/3 x)
    pool: int = 2               # average pooling of the stored 112 px images (56 px network)
    n_basis: int = 48           # principal modes the linear decoder starts from
    w_shape: float = 4.0        # weight of the 3-D loss on the centred grids (the shape)
    w_iso: float = 1.0
    w_contour: float = 1e-3
    w_align: float = 0.0        # weight of metric B itself (per-sample Procrustes + scale)
    augment: bool = False       # mirror left-right (grid columns too), permute / scale colours
    threads: int = 2
    max_steps: int = 0          # stop after this many steps (0: all epochs; smoke tests)
    wave_fraction: float = 0.5  # share of ``wave`` (flag) states in the training split (the
    #                             test splits keep the even split)
    max_yaw_deg: float = 35.0   # camera yaw range of the training split (the test splits keep
    #                             the default 35, so the rounds' metrics compare)
    init: str = ''              # warm start: hdmnet.pt of an earlier run, or an exported
    #                             hdmnet.onnx (BatchNorm then frozen); its record is kept

    def validate(self) -> None:
        for name in ('states', 'test_states', 'epochs', 'batch', 'width', 'threads', 'pool',
                     'n_basis'):
            if getattr(self, name) < 1:
                raise ValueError(f'{name}={getattr(self, name)}: expected >= 1')
        if not self.lr > 0:
            raise ValueError(f'lr={self.lr}: expected > 0')
        if not 0 <= self.wave_fraction <= 1:
            raise ValueError(f'wave_fraction={self.wave_fraction}: expected 0..1')
        if not 0 <= self.max_yaw_deg <= 60:
            raise ValueError(f'max_yaw_deg={self.max_yaw_deg}: expected 0..60')
        if min(self.w_shape, self.w_iso, self.w_contour, self.w_align, self.max_steps) < 0:
            raise ValueError('w_shape, w_iso, w_contour, w_align, max_steps: expected >= 0')


def _conv(i: int, o: int, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(i, o, 3, stride, 1, bias=False), nn.BatchNorm2d(o),
                         nn.ReLU(inplace=True))


class _Res(nn.Module):
    def __init__(self, c: int) -> None:
        super().__init__()
        self.a = _conv(c, c)
        self.b = nn.Sequential(nn.Conv2d(c, c, 3, 1, 1, bias=False), nn.BatchNorm2d(c))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.relu(x + self.b(self.a(x)))


class HDMNet(nn.Module):
    """(B, 3, s, s) [0, 1] images -> (B, GRID, GRID, 3); the images are first average-pooled
    by ``pool`` (the network proper sees s / pool px).  The decoder is linear from the code to
    the grid, initialised with the training grids' mean and principal modes (``basis``
    (n, GRID * GRID * 3), each mode scaled by its standard deviation) and trained with the rest:
    a learned deformation model in the camera frame."""

    def __init__(self, mean_grid: np.ndarray, basis: np.ndarray, width: int = 24,
                 pool: int = 1) -> None:
        super().__init__()
        w = width
        c = [w, 2 * w, 4 * w, 16 * w // 3, 16 * w // 3]
        self.pool, self.width = pool, width
        self.enc = nn.Sequential(_conv(3, c[0], 2), _conv(c[0], c[1], 2),
                                 _conv(c[1], c[2], 2), _Res(c[2]), _conv(c[2], c[3], 2),
                                 _Res(c[3]), _conv(c[3], c[4], 2))
        n = basis.shape[0]
        self.code = nn.Sequential(nn.Flatten(), nn.LazyLinear(256), nn.ReLU(inplace=True),
                                  nn.Linear(256, n))
        self.decoder = nn.Linear(n, H.GRID * H.GRID * 3)
        with torch.no_grad():
            self.decoder.weight.copy_(torch.as_tensor(np.asarray(basis, np.float32).T))
            self.decoder.bias.copy_(torch.as_tensor(np.asarray(mean_grid, np.float32).ravel()))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.pool > 1:
            x = Fn.avg_pool2d(x, self.pool)
        x = (x - 0.45) / 0.25
        return self.decoder(self.code(self.enc(x))).view(-1, H.GRID, H.GRID, 3)


def principal_modes(grids: np.ndarray, n: int, seed: int = 0, sample: int = 1000
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Mean (GRID, GRID, 3) and the first ``n`` principal modes (n, GRID * GRID * 3) of the
    grids (N, GRID, GRID, 3) (of a random ``sample`` of them), scaled by their std."""
    G = grids.reshape(len(grids), -1).astype(np.float64)
    pick = np.random.default_rng(seed).permutation(len(G))[:sample]
    mean = G.mean(axis=0)
    _, sv, Vt = np.linalg.svd(G[pick] - mean, full_matrices=False)
    k = min(n, len(sv))
    modes = np.zeros((n, G.shape[1]))
    modes[:k] = Vt[:k] * (sv[:k, None] / np.sqrt(len(pick)))
    return mean.reshape(grids.shape[1:]), modes


def _gauss_kernel(sigma: float = 1.0, r: int = 2) -> torch.Tensor:
    k = np.exp(-0.5 * (np.arange(-r, r + 1) / sigma) ** 2)
    k2 = np.outer(k, k) / np.outer(k, k).sum()
    return torch.as_tensor(k2, dtype=torch.float32)[None, None].repeat(3, 1, 1, 1)


def isometry_loss(pred: torch.Tensor, kernel: torch.Tensor) -> torch.Tensor:
    """Mean squared distance of the grid (B, n, n, 3) to its Gaussian-smoothed self."""
    g = pred.permute(0, 3, 1, 2)
    r = kernel.shape[-1] // 2
    smooth = Fn.conv2d(Fn.pad(g, (r, r, r, r), mode='replicate'), kernel, groups=3)
    return ((g - smooth) ** 2).sum(1).mean()


def soft_silhouette(pred: torch.Tensor) -> torch.Tensor:
    """(B, SIL, SIL) soft silhouette: Gaussian splats of every SIL_STEP-th node projected by
    the canonical camera at SIL px, 1 - exp(-sum)."""
    p = pred[:, ::SIL_STEP, ::SIL_STEP].reshape(pred.shape[0], -1, 3)
    f = H.CANON_FOCAL * SIL / H.INPUT_SIZE
    c = (SIL - 1) / 2
    z = p[..., 2].clamp(min=0.1)
    u, v = f * p[..., 0] / z + c, f * p[..., 1] / z + c
    ax = torch.arange(SIL, dtype=pred.dtype)
    gu = torch.exp(-0.5 * ((ax[None, None] - u[..., None]) / SIL_SIGMA) ** 2)   # B, N, W
    gv = torch.exp(-0.5 * ((ax[None, None] - v[..., None]) / SIL_SIGMA) ** 2)   # B, N, H
    dens = torch.einsum('bnh,bnw->bhw', gv, gu)
    return 1 - torch.exp(-dens)


def aligned_error(pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
    """Per-sample metric B (B,) of grids (B, n, n, 3) against the truth: the centred
    prediction Procrustes-aligned (reflections allowed) and scaled onto the centred truth,
    ||A - G|| / ||G||, as ``core.hdmnet.e3d_per_frame``.  The rotation and scale are the
    optimum's and carry no gradient (at the optimum the loss is stationary in them, so the
    gradient is that of the minimum itself)."""
    P = pred.reshape(pred.shape[0], -1, 3)
    G = gt.reshape(gt.shape[0], -1, 3)
    Pc, Gc = P - P.mean(1, keepdim=True), G - G.mean(1, keepdim=True)
    with torch.no_grad():
        U, sig, Vt = torch.linalg.svd((Pc.transpose(1, 2) @ Gc).double())
        R = (U @ Vt).to(P.dtype)
        scale = (sig.sum(1) / (Pc.double() ** 2).sum((1, 2)).clamp(min=1e-30)).to(P.dtype)
    A = scale[:, None, None] * (Pc @ R)
    num = ((A - Gc) ** 2).sum((1, 2))
    return torch.sqrt(num / (Gc ** 2).sum((1, 2)).clamp(min=1e-30) + 1e-12)


def losses(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor, kernel: torch.Tensor,
           cfg: TrainConfig) -> dict[str, torch.Tensor]:
    l3d = ((pred - gt) ** 2).sum(-1).mean()
    d = (pred - pred.mean(dim=(1, 2), keepdim=True)) - (gt - gt.mean(dim=(1, 2), keepdim=True))
    lshape = (d ** 2).sum(-1).mean()
    liso = isometry_loss(pred, kernel)
    lcon = ((soft_silhouette(pred) - mask) ** 2).mean() if cfg.w_contour > 0 \
        else torch.zeros(())
    lal = aligned_error(pred, gt).mean() if cfg.w_align > 0 else torch.zeros(())
    return {'total': l3d + cfg.w_shape * lshape + cfg.w_iso * liso + cfg.w_contour * lcon
            + cfg.w_align * lal, '3d': l3d, 'shape': lshape, 'iso': liso, 'contour': lcon,
            'align': lal}


def augment_batch(x: torch.Tensor, g: torch.Tensor, m: torch.Tensor, gen: torch.Generator
                  ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Random label-preserving changes of a batch: half the samples mirrored left-right (the
    image, the silhouette, x -> -x of the nodes and the grid's columns reversed, so that the
    material s = 0 edge stays on the left as in the renders; the canonical camera's principal
    point is the image centre), every sample's colour channels permuted and scaled by
    0.8-1.2.  No vertical mirror: it would turn training lights into the held-out lower ones."""
    B = x.shape[0]
    flip = torch.rand(B, generator=gen) < 0.5
    x, g, m = x.clone(), g.clone(), m.clone()
    x[flip] = x[flip].flip(-1)
    m[flip] = m[flip].flip(-1)
    gf = g[flip].flip(2)
    gf[..., 0] = -gf[..., 0]
    g[flip] = gf
    perm = torch.argsort(torch.rand(B, 3, generator=gen), dim=1)
    x = x[torch.arange(B)[:, None], perm]
    gain = 0.8 + 0.4 * torch.rand(B, 3, 1, 1, generator=gen)
    return (x * gain).clamp(0, 1), g, m


def _masks_small(masks: np.ndarray) -> np.ndarray:
    import cv2
    return np.stack([cv2.resize(m.astype(np.float32), (SIL, SIL), interpolation=cv2.INTER_AREA)
                     for m in masks])


def _to_input(images: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(images.transpose(0, 3, 1, 2))).float() / 255


def split_configs(cfg: TrainConfig) -> dict[str, D.HDMDataConfig]:
    out = {'train': D.HDMDataConfig(split='train', samples=cfg.states, seed=cfg.seed,
                                    wave_fraction=cfg.wave_fraction,
                                    max_yaw_deg=cfg.max_yaw_deg)}
    for s in ('test', 'heldout-texture', 'heldout-light'):
        out[s] = D.HDMDataConfig(split=s, samples=cfg.test_states, seed=cfg.seed)
    return out


def baselines(grids: np.ndarray) -> dict[str, np.ndarray]:
    """Per-sample e3D of the rest shape (the flat sheet) and of the ground truth flattened onto
    its own plane (an oracle flat shape)."""
    from ..core.metrics import flat_shape
    rest = np.broadcast_to(D.rest_grid().reshape(1, -1, 3), (len(grids), H.GRID ** 2, 3))
    G = grids.reshape(len(grids), -1, 3)
    flat = np.stack([flat_shape(g) for g in G])
    return {'rest': H.e3d_per_frame(rest, G), 'flat': H.e3d_per_frame(flat, G)}


def split_metrics(pred: np.ndarray, data: dict[str, np.ndarray]) -> dict[str, Any]:
    """e3D (metric B) of predictions (N, GRID, GRID, 3) on one split: mean, per texture and per
    light, the baselines, and the depth RMSE (m) of the nodes."""
    G = data['grids'].reshape(len(pred), -1, 3)
    e = H.e3d_per_frame(pred.reshape(len(pred), -1, 3), G)
    base = baselines(data['grids'])
    out: dict[str, Any] = {'e3d': float(e.mean()), 'e3d_median': float(np.median(e)),
                           'rest': float(base['rest'].mean()), 'flat': float(base['flat'].mean()),
                           'depth_rmse_m': float(np.sqrt(np.mean(
                               (pred[..., 2] - data['grids'][..., 2]) ** 2))),
                           'samples': int(len(pred))}
    for key, names in (('texture', D.TEXTURES), ('light', tuple(D.LIGHTS))):
        out[f'per_{key}'] = {names[i]: {'e3d': float(e[data[key] == i].mean()),
                                        'rest': float(base['rest'][data[key] == i].mean()),
                                        'samples': int((data[key] == i).sum())}
                             for i in np.unique(data[key])}
    return out


SOURCES = ('learning/hdmnet_train.py', 'io/synth_hdmnet.py', 'io/synth.py', 'core/hdmnet.py')


def _git_commit() -> str:
    """HEAD, with ``+modified`` when the sources that make the model differ from it."""
    root = Path(__file__).resolve().parent.parent
    try:
        head = subprocess.run(['git', 'rev-parse', 'HEAD'], capture_output=True, text=True,
                              cwd=root, timeout=10, check=True).stdout.strip()
        dirty = subprocess.run(['git', 'status', '--porcelain', '--', *SOURCES],
                               capture_output=True, text=True, cwd=root, timeout=10,
                               check=True).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return 'unknown'
    return head + ('+modified' if dirty else '')


def _sources_sha256() -> dict[str, str]:
    root = Path(__file__).resolve().parent.parent
    return {s: hashlib.sha256((root / s).read_bytes()).hexdigest() for s in SOURCES}


def train(cfg: TrainConfig, out: str | Path, command: list[str] | None = None,
          data: dict[str, dict[str, np.ndarray]] | None = None,
          log: Callable[[str], None] = print) -> dict[str, Any]:
    """Render the data, train, export ``out/hdmnet.onnx`` and write ``out/hdmnet.json`` (seed,
    data configs, command, git commit, metrics).  Returns the JSON's dict."""
    cfg.validate()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(cfg.seed)
    torch.set_num_threads(cfg.threads)
    rng = np.random.default_rng(cfg.seed)
    t0 = time.perf_counter()
    confs = split_configs(cfg)
    if data is None:
        data = {}
        for name, dc in confs.items():
            data[name] = D.make_dataset(dc)
            log(f'rendered {name}: {dc.samples} samples ({time.perf_counter() - t0:.0f} s)')
    render_s = time.perf_counter() - t0
    tr = data['train']
    mean_grid, basis = principal_modes(tr['grids'], cfg.n_basis, cfg.seed)
    model = HDMNet(mean_grid, basis, cfg.width, cfg.pool)
    x_all = _to_input(tr['images'])
    g_all = torch.from_numpy(tr['grids'])
    m_all = torch.from_numpy(_masks_small(tr['masks']))
    model(x_all[:2])                                 # materialise the lazy layer
    init_record: dict[str, Any] | None = None
    freeze_bn = False
    if cfg.init:
        init = Path(cfg.init)
        if not init.is_file():
            raise FileNotFoundError(f'init={cfg.init}: no such checkpoint')
        if init.suffix == '.onnx':
            load_onnx_weights(model, init)
            freeze_bn = True
        else:
            model.load_state_dict(torch.load(init)['state_dict'])
        rec = init.with_suffix('.json')
        init_record = {'path': str(init), 'sha256': hashlib.sha256(init.read_bytes()).hexdigest(),
                       'record': json.loads(rec.read_text()) if rec.is_file() else None}
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=1e-4)
    n = len(x_all)
    steps_per_epoch = max(1, n // cfg.batch)
    total = steps_per_epoch * cfg.epochs
    if cfg.max_steps:
        total = min(total, cfg.max_steps)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=cfg.lr, total_steps=total,
                                                pct_start=0.15)
    kernel = _gauss_kernel()
    gen = torch.Generator().manual_seed(cfg.seed)
    step, t1, history = 0, time.perf_counter(), []
    model.train()
    if freeze_bn:                        # the ONNX weights hold BatchNorm folded in
        for mod in model.modules():
            if isinstance(mod, nn.BatchNorm2d):
                mod.eval()
    while step < total:
        order = rng.permutation(n)
        acc: dict[str, float] = {}
        for b in range(steps_per_epoch):
            if step >= total:
                break
            idx = torch.from_numpy(order[b * cfg.batch:(b + 1) * cfg.batch])
            xb, gb, mb = x_all[idx], g_all[idx], m_all[idx]
            if cfg.augment:
                xb, gb, mb = augment_batch(xb, gb, mb, gen)
            L = losses(model(xb), gb, mb, kernel, cfg)
            opt.zero_grad()
            L['total'].backward()
            opt.step()
            sched.step()
            step += 1
            for k, v in L.items():
                acc[k] = acc.get(k, 0.0) + float(v.detach()) / steps_per_epoch
        history.append({k: round(v, 7) for k, v in acc.items()})
        log(f'epoch {len(history)}/{cfg.epochs} step {step}/{total} '
            + ' '.join(f'{k} {v:.3g}' for k, v in acc.items())
            + f' ({time.perf_counter() - t1:.0f} s)')
    train_s = time.perf_counter() - t1
    model.eval()
    metrics: dict[str, Any] = {}
    with torch.no_grad():
        for name in ('test', 'heldout-texture', 'heldout-light', 'train'):
            d = data[name] if name != 'train' else {k: v[:cfg.test_states]
                                                      for k, v in tr.items()}
            pred = np.concatenate([model(_to_input(d['images'][i:i + 64])).numpy()
                                   for i in range(0, len(d['images']), 64)])
            metrics[name] = split_metrics(pred, d)
            log(f'{name}: e3D {metrics[name]["e3d"]:.4f} (rest {metrics[name]["rest"]:.4f}, '
                f'flat {metrics[name]["flat"]:.4f})')
    torch.save({'state_dict': model.state_dict(), 'config': asdict(cfg)}, out / 'hdmnet.pt')
    onnx_path = out / 'hdmnet.onnx'
    export_onnx(model, onnx_path, cfg.pool * H.INPUT_SIZE // confs['train'].stored)
    blob = onnx_path.read_bytes()
    meta = {'model': 'hdmnet', 'format': 'onnx', 'input': {
                'name': 'image', 'shape': [1, 3, H.INPUT_SIZE, H.INPUT_SIZE],
                'range': '[0, 1] rgb', 'canonical_focal_px': H.CANON_FOCAL},
            'output': {'name': 'points', 'shape': [1, H.GRID, H.GRID, 3],
                       'frame': 'canonical camera optical frame, metres'},
            'seed': cfg.seed, 'train_config': asdict(cfg),
            'data': {k: asdict(v) for k, v in confs.items()},
            'textures': {'train': list(D.TRAIN_TEXTURES), 'heldout': list(D.HELDOUT_TEXTURES)},
            'lights': {'train': list(D.TRAIN_LIGHTS), 'heldout': list(D.HELDOUT_LIGHTS)},
            'command': command if command is not None else sys.argv,
            'git_commit': _git_commit(), 'sources_sha256': _sources_sha256(),
            'torch': torch.__version__,
            'parameters': int(sum(p.numel() for p in model.parameters())),
            'bytes': len(blob), 'sha256': hashlib.sha256(blob).hexdigest(),
            'init': init_record,
            'render_s': round(render_s, 1), 'train_s': round(train_s, 1), 'steps': step,
            'history': history, 'metrics': metrics}
    (out / 'hdmnet.json').write_text(json.dumps(meta, indent=1) + '\n')
    return meta


def load_onnx_weights(model: HDMNet, path: Path) -> None:
    """Load an exported hdmnet.onnx (``export_onnx``: BatchNorm folded into the convolutions)
    into ``model`` (same width and pool; the lazy layer materialised): each convolution takes
    the folded weights and its BatchNorm becomes the identity plus the folded bias (running
    mean 0, variance 1 - eps, scale 1).  Train it with the BatchNorm layers in eval mode."""
    import onnx
    from onnx import numpy_helper
    g = onnx.load(str(path)).graph
    init = {t.name: numpy_helper.to_array(t) for t in g.initializer}
    convs = [n for n in g.node if n.op_type == 'Conv']
    pairs = [(m[0], m[1]) for m in (list(mod.children()) for mod in model.enc.modules()
                                    if isinstance(mod, nn.Sequential))
             if len(m) >= 2 and isinstance(m[0], nn.Conv2d) and isinstance(m[1], nn.BatchNorm2d)]
    if len(convs) != len(pairs):
        raise ValueError(f'{path}: {len(convs)} convolutions, the model has {len(pairs)}')
    with torch.no_grad():
        for node, (conv, bn) in zip(convs, pairs):
            w = torch.as_tensor(np.array(init[node.input[1]]))
            if w.shape != conv.weight.shape:
                raise ValueError(f'{path}: convolution {tuple(w.shape)} does not fit '
                                 f'{tuple(conv.weight.shape)} (another width?)')
            conv.weight.copy_(w)
            b = init[node.input[2]] if len(node.input) > 2 else np.zeros(w.shape[0], np.float32)
            bn.weight.fill_(1.0)
            bn.bias.copy_(torch.as_tensor(np.array(b)))
            bn.running_mean.zero_()
            bn.running_var.fill_(1.0 - bn.eps)
        sd = model.state_dict()
        for k in ('code.1.weight', 'code.1.bias', 'code.3.weight', 'code.3.bias',
                  'decoder.weight', 'decoder.bias'):
            v = torch.as_tensor(np.array(init[k]))
            if v.shape != sd[k].shape:
                raise ValueError(f'{path}: {k} {tuple(v.shape)} does not fit '
                                 f'{tuple(sd[k].shape)}')
            sd[k].copy_(v)


def export_onnx(model: HDMNet, path: Path, pool: int) -> None:
    """The model with its ``pool`` x ``pool`` average-pooling stem (the training data's
    downsampling and the model's own), (1, 3, INPUT_SIZE, INPUT_SIZE) in."""
    n = model.decoder.weight.shape[1]
    m = HDMNet(np.zeros((H.GRID, H.GRID, 3)), np.zeros((n, H.GRID * H.GRID * 3)),
               model.width, pool)
    m(torch.zeros(1, 3, H.INPUT_SIZE, H.INPUT_SIZE))
    m.load_state_dict(model.state_dict())
    m.eval()
    x = torch.zeros(1, 3, H.INPUT_SIZE, H.INPUT_SIZE)
    torch.onnx.export(m, (x,), str(path), input_names=['image'], output_names=['points'],
                      dynamo=False, opset_version=17)


def main_config(**kw: Any) -> TrainConfig:
    return replace(TrainConfig(), **{k: v for k, v in kw.items() if v is not None})
