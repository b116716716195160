"""Deterministic 2D deforming image sequences with ground-truth dense tracks (tracking benchmark).

A textured sheet larger than the view is deformed by a smooth, time-varying displacement field
(global similarity motion plus Gaussian-RBF bumps, total motion up to ``max_motion_px``), rendered
by forward-mapping its mesh (so the ground truth is exact, not an inverted warp), with a mild
illumination change (global gain and bias, a slow spatial gradient) and Gaussian noise.  An
optional occluder (a disc with its own texture) crosses the view for ``occluder_frames`` frames.

Every pixel of the reference frame (frame 0) is a track; ``W`` (2F x P) holds their true
positions, ``V`` (F x P) whether they are in view and not covered by the occluder, ``occluded``
(F x P) whether the occluder covers them.  Track ids follow the tracker's convention
``y * width + x``.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .synth import _texture, rasterise


@dataclass(frozen=True)
class DeformConfig:
    width: int = 320
    height: int = 256
    frames: int = 60
    seed: int = 0
    max_motion_px: float = 60.0   # largest displacement of a reference pixel over the sequence
    bumps: int = 16               # Gaussian-RBF deformation components
    noise: float = 2.0            # image noise sigma (intensity units)
    illumination: float = 0.08    # relative gain change amplitude (bias and gradient scale too)
    occluder_frames: int = 0      # 0: no occluder
    occluder_radius: float = 0.14  # fraction of the image width
    contrast: float = 0.15        # texture contrast (1: intensity std ~45)
    bump_scale: float = 0.12      # RBF width, fraction of the smaller image side
    strain: float = 0.4           # bound on the non-rigid displacement gradient

    def validate(self) -> None:
        if not (32 <= self.width <= 1920 and 32 <= self.height <= 1080):
            raise ValueError(f'width x height = {self.width}x{self.height}: expected 32..1920 x '
                             '32..1080')
        if not 2 <= self.frames <= 2000:
            raise ValueError(f'frames={self.frames}: expected 2..2000')
        if self.occluder_frames < 0 or self.occluder_frames > self.frames - 1:
            raise ValueError(f'occluder_frames={self.occluder_frames}: expected 0..frames-1')
        if self.max_motion_px < 0 or self.noise < 0:
            raise ValueError('max_motion_px and noise must be >= 0')
        if not 0 <= self.strain < 0.8:
            raise ValueError(f'strain={self.strain}: expected 0..0.8 (larger folds the warp)')


@dataclass
class DeformSequence:
    config: DeformConfig
    images: np.ndarray     # (F, H, W) uint8 grey
    W: np.ndarray          # (2F, P) true track positions, pixels (every reference pixel)
    V: np.ndarray          # (F, P) bool: in view and not occluded
    occluded: np.ndarray   # (F, P) bool: covered by the occluder
    track_ids: np.ndarray  # (P,) uint32, y * width + x

    def flow(self, f: int) -> np.ndarray:
        """True reference->frame f flow (H, W, 2)."""
        h, w = self.config.height, self.config.width
        x = self.W[0::2][0].reshape(h, w)
        y = self.W[1::2][0].reshape(h, w)
        return np.stack([self.W[2 * f].reshape(h, w) - x,
                         self.W[2 * f + 1].reshape(h, w) - y], axis=-1)


def _motion(cfg: DeformConfig, rng: np.random.Generator):
    """Displacement function d(points (N, 2), frame) -> (N, 2), smooth in space and time: a
    global similarity motion scaled so the largest reference-pixel displacement is about
    ``max_motion_px``, plus Gaussian-RBF bumps whose local strain stays below ``strain`` (so the
    warp never folds)."""
    w, h, F = cfg.width, cfg.height, cfg.frames
    c = np.array([(w - 1) / 2, (h - 1) / 2])
    tt = np.arange(F) / max(F - 1, 1)          # 0..1 over the sequence
    ph = rng.uniform(0, 2 * np.pi, (4,))
    ramp = np.minimum(tt * 4, 1)
    rot = np.radians(6.0) * np.sin(2 * np.pi * 0.7 * tt + ph[0]) * ramp
    scale = 1.0 + 0.05 * np.sin(2 * np.pi * 0.5 * tt + ph[1]) * ramp
    trans = np.stack([0.45 * np.sin(2 * np.pi * 0.8 * tt + ph[2]) - 0.45 * np.sin(ph[2]),
                      0.30 * np.sin(2 * np.pi * 0.6 * tt + ph[3]) - 0.30 * np.sin(ph[3])], 1)
    centres = rng.uniform([0.05 * w, 0.05 * h], [0.95 * w, 0.95 * h], (cfg.bumps, 2))
    sig = rng.uniform(0.7, 1.3, cfg.bumps) * cfg.bump_scale * min(w, h)
    direction = rng.normal(size=(cfg.bumps, 2))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    amp = direction * (cfg.strain * sig / 1.2)[:, None]
    freq = rng.uniform(0.6, 1.6, cfg.bumps)
    phase = rng.uniform(0, 2 * np.pi, cfg.bumps)
    coef = np.sin(2 * np.pi * freq[None] * tt[:, None] + phase[None]) - np.sin(phase)[None]

    def glob(p: np.ndarray, f: int) -> np.ndarray:
        q = p - c
        ca, sa = np.cos(rot[f]), np.sin(rot[f])
        return scale[f] * (q @ np.array([[ca, sa], [-sa, ca]])) - q + trans[f] * min(w, h)

    def bumps(p: np.ndarray, f: int) -> np.ndarray:
        g = np.exp(-((p[:, None, :] - centres[None]) ** 2).sum(-1) / (2 * sig ** 2))
        return (g * coef[f][None]) @ amp

    xs, ys = np.meshgrid(np.linspace(0, w - 1, 41), np.linspace(0, h - 1, 33))
    probe = np.stack([xs.ravel(), ys.ravel()], 1)
    peak_g = max(np.abs(glob(probe, f)).max() for f in range(F))
    peak_b = max(np.abs(bumps(probe, f)).max() for f in range(F))
    k = max(cfg.max_motion_px - peak_b, 0.0) / peak_g if peak_g > 0 else 0.0
    return lambda p, f: k * glob(p, f) + bumps(p, f)


def generate_deforming(cfg: DeformConfig) -> DeformSequence:
    """Render the sequence and its ground truth (deterministic for a given config)."""
    cfg.validate()
    rng = np.random.default_rng(cfg.seed)
    w, h, F = cfg.width, cfg.height, cfg.frames
    texture = cv2.cvtColor(_texture(rng, 1024), cv2.COLOR_RGB2GRAY).astype(np.float32)
    texture = 128 + cfg.contrast * (texture - 128)
    occ_tex = cv2.cvtColor(_texture(rng, 256), cv2.COLOR_RGB2GRAY)
    d = _motion(cfg, rng)
    # the sheet: a mesh reaching well past the view so it always covers it
    margin = cfg.max_motion_px * 1.6 + 16
    step = 4.0
    gx = np.arange(-margin, w - 1 + margin + step, step)
    gy = np.arange(-margin, h - 1 + margin + step, step)
    mx, my = np.meshgrid(gx, gy)
    verts = np.stack([mx.ravel(), my.ravel()], 1)
    nx, ny = gx.size, gy.size
    i = np.arange(nx * ny).reshape(ny, nx)
    a, b, c_, e = i[:-1, :-1].ravel(), i[:-1, 1:].ravel(), i[1:, :-1].ravel(), i[1:, 1:].ravel()
    tris = np.concatenate([np.stack([a, b, c_], 1), np.stack([b, e, c_], 1)])
    span = np.array([gx[-1] - gx[0], gy[-1] - gy[0]])
    tex_uv = (verts - [gx[0], gy[0]]) / span.max() * (texture.shape[0] - 1)
    ys, xs = np.mgrid[0:h, 0:w]
    ref = np.stack([xs.ravel(), ys.ravel()], 1).astype(float)
    P = ref.shape[0]
    images = np.empty((F, h, w), np.uint8)
    Wt = np.empty((2 * F, P))
    V = np.empty((F, P), bool)
    occluded = np.zeros((F, P), bool)
    occ_start = (F - cfg.occluder_frames) // 2
    r_occ = cfg.occluder_radius * w
    ramp = (xs / max(w - 1, 1) - 0.5).astype(np.float32)
    tt = np.arange(F) / max(F - 1, 1)
    for f in range(F):
        uv = verts + d(verts, f)
        zbuf, att = rasterise(uv, np.zeros(len(uv)), tex_uv, tris, w, h)
        st = np.nan_to_num(att).astype(np.float32)
        img = cv2.remap(texture, st[..., 0], st[..., 1], cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_REFLECT).astype(np.float32)
        gain = 1.0 + cfg.illumination * np.sin(2 * np.pi * 0.9 * tt[f])
        bias = 100.0 * cfg.illumination * np.sin(2 * np.pi * 0.6 * tt[f] + 1.0)
        img = img * (gain + cfg.illumination * tt[f] * ramp) + bias
        pos = ref + d(ref, f)
        Wt[2 * f], Wt[2 * f + 1] = pos[:, 0], pos[:, 1]
        inside = (pos[:, 0] >= 0) & (pos[:, 0] <= w - 1) & (pos[:, 1] >= 0) & (pos[:, 1] <= h - 1)
        if cfg.occluder_frames and occ_start <= f < occ_start + cfg.occluder_frames:
            s = (f - occ_start + 0.5) / cfg.occluder_frames
            centre = np.array([-r_occ + s * (w + 2 * r_occ), 0.35 * h + 0.3 * h * s])
            disc = (xs - centre[0]) ** 2 + (ys - centre[1]) ** 2 <= r_occ ** 2
            ox = np.clip(xs - centre[0] + 128, 0, 255).astype(np.float32)
            oy = np.clip(ys - centre[1] + 128, 0, 255).astype(np.float32)
            occ_img = cv2.remap(occ_tex, ox, oy, cv2.INTER_LINEAR).astype(np.float32)
            img = np.where(disc, 0.8 * occ_img + 20, img)
            occluded[f] = ((pos - centre) ** 2).sum(1) <= r_occ ** 2
        if cfg.noise > 0:
            img = img + rng.normal(0, cfg.noise, img.shape)
        images[f] = np.clip(np.rint(img), 0, 255).astype(np.uint8)
        V[f] = inside & ~occluded[f]
    ids = (ys.ravel() * w + xs.ravel()).astype(np.uint32)
    return DeformSequence(config=cfg, images=images, W=Wt, V=V, occluded=occluded,
                          track_ids=ids)
