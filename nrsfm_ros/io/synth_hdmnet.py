"""Training and test images for HDM-Net (METHODS.md section 8): a 1.0 x 0.7 m sheet with a flat
rest shape in many deformation states, rendered with procedural textures, Lambertian (and, for
the endoscopy texture, specular) shading under several light directions, seen from varied
camera poses by the canonical HDM-Net camera (``core.hdmnet``: a square image, focal
``CANON_FOCAL`` px at ``INPUT_SIZE``).

Deformation families (both are the project's synthetic surfaces, so a model trained here applies
to ``nrsfm-ros synth --surface sheet|flag`` renders): ``bend`` (the isometric cylinder bend of
``synth``'s sheet, random curvature and axis) and ``wave`` (``synth``'s waving flag at a random
time, phase and amplitude).

Split: a state, a texture instance, a light and a pose are drawn per sample from seeded streams;
train and test draw their states from disjoint seeds.  Texture families ``TRAIN_TEXTURES`` are
seen in training (test samples use held-out instances of them); ``HELDOUT_TEXTURES`` never are.
Illuminations ``TRAIN_LIGHTS`` are seen in training, ``HELDOUT_LIGHTS`` never are.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..core import hdmnet as H
from . import synth

TRAIN_TEXTURES = ('blobs', 'checker', 'stripes', 'cloth', 'endoscopy')
HELDOUT_TEXTURES = ('marble',)
TEXTURES = TRAIN_TEXTURES + HELDOUT_TEXTURES
# light direction (camera frame, towards the light), ambient, diffuse; shading is two-sided
LIGHTS: dict[str, tuple[tuple[float, float, float], float, float]] = {
    'synth': ((0.3, -0.4, -1.0), 0.35, 0.65),     # nrsfm_ros.io.synth's light
    'front': ((0.0, 0.0, -1.0), 0.30, 0.70),
    'left': ((-0.8, -0.2, -0.6), 0.25, 0.75),
    'top': ((0.1, -0.9, -0.45), 0.30, 0.70),
    'right': ((0.85, 0.1, -0.5), 0.25, 0.75),
    'bottom-left': ((-0.55, 0.7, -0.45), 0.30, 0.70),
    'grazing': ((0.95, -0.15, -0.25), 0.20, 0.80),
}
TRAIN_LIGHTS = ('synth', 'front', 'left', 'top', 'right')
HELDOUT_LIGHTS = ('bottom-left', 'grazing')
FAMILIES = ('bend', 'wave')
SPLITS = ('train', 'test', 'heldout-texture', 'heldout-light')
TEX_SIZE = 256
_SPLIT_SEED = {'train': 0, 'test': 1, 'heldout-texture': 2, 'heldout-light': 3}


@dataclass(frozen=True)
class HDMDataConfig:
    """What ``make_dataset`` renders: ``samples`` images of one split at ``size`` px (the model's
    input is ``core.hdmnet.INPUT_SIZE``; training stores them area-downsampled by ``stored``),
    deformation amplitude up to ``max_amplitude``, camera yaw/pitch up to ``max_yaw_deg`` /
    ``max_pitch_deg``, roll up to ``max_roll_deg``, distance so that the rest sheet spans
    ``fill`` of the image width; ``wave_fraction``: the share of samples drawn from the
    ``wave`` family (the rest ``bend``)."""
    split: str = 'train'
    samples: int = 4000
    seed: int = 0
    stored: int = 112
    max_amplitude: float = 2.0
    max_yaw_deg: float = 35.0
    max_pitch_deg: float = 25.0
    max_roll_deg: float = 10.0
    fill: tuple[float, float] = (0.55, 0.85)
    noise: float = 3.0
    textures_per_family: int = 24
    wave_fraction: float = 0.5

    def validate(self) -> None:
        if self.split not in SPLITS:
            raise ValueError(f'split={self.split!r}: expected one of {SPLITS}')
        if not 1 <= self.samples <= 200_000:
            raise ValueError(f'samples={self.samples}: expected 1..200000')
        if self.stored < 16 or H.INPUT_SIZE % self.stored:
            raise ValueError(f'stored={self.stored}: expected a divisor of {H.INPUT_SIZE} '
                             '>= 16')
        if not 0 <= self.max_amplitude <= synth.MAX_AMPLITUDE:
            raise ValueError(f'max_amplitude={self.max_amplitude}: expected 0..'
                             f'{synth.MAX_AMPLITUDE}')
        for name in ('max_yaw_deg', 'max_pitch_deg', 'max_roll_deg'):
            if not 0 <= getattr(self, name) <= 60:
                raise ValueError(f'{name}={getattr(self, name)}: expected 0..60')
        lo, hi = self.fill
        if not 0.2 <= lo <= hi <= 1.0:
            raise ValueError(f'fill={self.fill}: expected 0.2 <= lo <= hi <= 1')
        if not self.noise >= 0:
            raise ValueError(f'noise={self.noise}: expected >= 0')
        if not 0 <= self.wave_fraction <= 1:
            raise ValueError(f'wave_fraction={self.wave_fraction}: expected 0..1')
        if self.textures_per_family < 1:
            raise ValueError(f'textures_per_family={self.textures_per_family}: expected >= 1')


# ---------------------------------------------------------------- states

def sheet_grid(family: str, tau: float, amp: float, phase: np.ndarray,
               n: int = H.GRID) -> np.ndarray:
    """(n, n, 3) object-frame points of the sheet's n x n material grid (row: t, column: s)."""
    if family not in FAMILIES:
        raise ValueError(f'family={family!r}: expected one of {FAMILIES}')
    s, t = (a.ravel() for a in np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n)))
    kind = 'sheet' if family == 'bend' else 'flag'
    X = synth._surface(kind, s, t, tau, amp, phase)
    if family == 'wave':                  # the flag is not centred: centre it like the sheet
        X = X - [0.0, 0.0, X[:, 2].mean()]
    return X.reshape(n, n, 3)


def rest_grid(n: int = H.GRID) -> np.ndarray:
    """(n, n, 3) the flat rest shape in the object frame (z = 0)."""
    return sheet_grid('bend', 0.0, 0.0, np.zeros(3), n)


# ---------------------------------------------------------------- textures

def texture(family: str, seed: int, size: int = TEX_SIZE) -> np.ndarray:
    """(size, size, 3) uint8 RGB instance ``seed`` of a texture family."""
    rng = np.random.default_rng([seed, TEXTURES.index(family) if family in TEXTURES else -1])
    if family == 'blobs':
        return synth._texture(rng, size)
    y, x = (np.mgrid[0:size, 0:size].astype(np.float32) + 0.5) / size
    c0, c1 = rng.uniform(20, 235, (2, 3)).astype(np.float32)
    fine = _noise(rng, size, 32, 3)
    if family == 'checker':
        n = rng.integers(4, 13)
        a = rng.uniform(0, np.pi)
        u, v = x * np.cos(a) - y * np.sin(a), x * np.sin(a) + y * np.cos(a)
        m = ((np.floor(u * n) + np.floor(v * n)) % 2)[..., None]
        img = c0 * m + c1 * (1 - m) + 12 * fine
    elif family == 'stripes':
        freq = rng.uniform(4, 14)
        a = rng.uniform(0, np.pi)
        w = 0.5 + 0.5 * np.sin(2 * np.pi * freq * (x * np.cos(a) + y * np.sin(a))
                               + 2.0 * _noise(rng, size, 4, 1)[..., 0])
        img = c0 * w[..., None] + c1 * (1 - w[..., None]) + 12 * fine
    elif family == 'cloth':
        fx, fy = rng.uniform(20, 45, 2)
        warp = 0.5 + 0.5 * np.sin(2 * np.pi * fx * x) * np.sign(np.sin(2 * np.pi * fy * y))
        plaid = (np.sin(2 * np.pi * rng.uniform(2, 5) * x) > 0.6) | (
            np.sin(2 * np.pi * rng.uniform(2, 5) * y) > 0.6)
        base = np.where(plaid[..., None], c1, c0)
        img = base * (0.7 + 0.3 * warp[..., None]) + 10 * fine
    elif family == 'endoscopy':
        img = _endoscopy(rng, size)
    elif family == 'marble':
        turb = 3.0 * _noise(rng, size, 6, 1)[..., 0] + 1.5 * _noise(rng, size, 24, 1)[..., 0]
        vein = np.abs(np.sin(2 * np.pi * rng.uniform(1.5, 4) * (x + 0.6 * y) + turb)) ** 0.3
        base = np.array([225, 215, 200], np.float32) * rng.uniform(0.8, 1.05)
        img = base * (0.45 + 0.55 * vein[..., None]) + 8 * fine
    else:
        raise ValueError(f'texture family={family!r}: expected one of {TEXTURES}')
    return np.clip(img, 0, 255).astype(np.uint8)


def _noise(rng: np.random.Generator, size: int, scale: int, ch: int) -> np.ndarray:
    n = rng.normal(size=(scale, scale, ch)).astype(np.float32)
    out = cv2.resize(n, (size, size), interpolation=cv2.INTER_CUBIC)
    return out.reshape(size, size, ch) / (out.std() + 1e-6)


def _endoscopy(rng: np.random.Generator, size: int) -> np.ndarray:
    """Reddish mucosa with low-frequency tint, dark branching vessels and baked wet glints."""
    base = np.array([190, 80, 75], np.float32) * rng.uniform(0.85, 1.1, 3).astype(np.float32)
    img = base * (0.8 + 0.12 * _noise(rng, size, 5, 1) + 0.05 * _noise(rng, size, 40, 1))
    vessels = np.zeros((size, size), np.float32)
    for _ in range(int(rng.integers(6, 12))):
        p = rng.uniform(0, size, 2)
        a = rng.uniform(0, 2 * np.pi)
        width = float(rng.uniform(1.5, 4.5))
        for _ in range(int(rng.integers(2, 4))):          # a vessel and its branches
            pts = [p.copy()]
            for _ in range(40):
                a += rng.normal(0, 0.25)
                p = p + 4.0 * np.array([np.cos(a), np.sin(a)])
                pts.append(p.copy())
            cv2.polylines(vessels, [np.asarray(pts, np.int32)], False, 1.0,
                          max(1, int(round(width))), cv2.LINE_AA)
            p, a, width = pts[int(rng.integers(5, 35))], a + rng.choice([-1, 1]) * 0.9, \
                max(1.0, 0.6 * width)
    vessels = cv2.GaussianBlur(vessels, (0, 0), 0.8)[..., None]
    img = img * (1 - 0.55 * vessels) + np.array([90, 10, 25], np.float32) * 0.2 * vessels
    glint = np.zeros((size, size), np.float32)
    for _ in range(int(rng.integers(10, 25))):
        c = tuple(int(v) for v in rng.integers(0, size, 2))
        cv2.ellipse(glint, c, (int(rng.integers(1, 4)), int(rng.integers(1, 3))),
                    float(rng.uniform(0, 180)), 0, 360, 1.0, -1, cv2.LINE_AA)
    glint = cv2.GaussianBlur(glint, (0, 0), 1.0)[..., None]
    return img * (1 - glint) + 250 * glint


# ---------------------------------------------------------------- rendering

def canonical_K(size: int = H.INPUT_SIZE) -> np.ndarray:
    """The canonical camera's intrinsics at an image of ``size`` x ``size`` px."""
    f = H.CANON_FOCAL * size / H.INPUT_SIZE
    c = (size - 1) / 2
    return np.array([[f, 0, c], [0, f, c], [0, 0, 1.0]])


def pose(yaw: float, pitch: float, roll: float, distance: float,
         target: np.ndarray) -> np.ndarray:
    """T_camera_object of a camera ``distance`` m from ``target`` (object frame), rotated by
    yaw / pitch about the object and rolled about its optical axis (radians)."""
    c = distance * np.array([np.sin(yaw) * np.cos(pitch), np.sin(pitch),
                             -np.cos(yaw) * np.cos(pitch)]) + target
    T = synth._look_at(c, target.astype(float))
    cr, sr = np.cos(roll), np.sin(roll)
    Rz = np.array([[cr, -sr, 0], [sr, cr, 0], [0, 0, 1.0]])
    T[:3] = Rz @ T[:3]
    return T


_TRIS = None


def _grid_tris() -> np.ndarray:
    global _TRIS
    if _TRIS is None:
        _TRIS = synth._grid_mesh('sheet', H.GRID, H.GRID)[2]
    return _TRIS


def render(grid_cam: np.ndarray, tex: np.ndarray, light: str, size: int = H.INPUT_SIZE,
           background: np.ndarray | None = None, specular: float = 0.0,
           K: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Render the camera-frame grid (GRID, GRID, 3) with texture ``tex`` under ``light`` into a
    ``size`` x ``size`` image by the canonical camera (or ``K``).  Returns the rgb8 image and the
    surface mask (bool)."""
    if light not in LIGHTS:
        raise ValueError(f'light={light!r}: expected one of {tuple(LIGHTS)}')
    K = canonical_K(size) if K is None else K
    X = grid_cam.reshape(-1, 3)
    n = H.GRID
    s, t = (a.ravel() for a in np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n)))
    tris = _grid_tris()
    normals = synth._vertex_normals(X, tris)
    d, amb, dif = LIGHTS[light]
    ld = np.asarray(d) / np.linalg.norm(d)
    shade = amb + dif * np.abs(normals @ ld)
    spec = np.zeros_like(shade)
    if specular > 0:                     # Blinn-Phong, the viewer at the camera centre
        view = -X / np.linalg.norm(X, axis=1, keepdims=True)
        h = (view + ld) / np.linalg.norm(view + ld, axis=1, keepdims=True)
        spec = specular * np.abs(np.einsum('ij,ij->i', normals, h)) ** 40
    uv = synth._project(K, X)
    zbuf, att = synth.rasterise(uv, X[:, 2], np.stack([s, t, shade, spec], 1), tris, size, size)
    mask = np.isfinite(zbuf)
    st = np.nan_to_num(att[..., :2])
    img = cv2.remap(tex, (st[..., 0] * (tex.shape[1] - 1)).astype(np.float32),
                    (st[..., 1] * (tex.shape[0] - 1)).astype(np.float32), cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_REFLECT).astype(np.float32)
    img = img * np.nan_to_num(att[..., 2:3]) + 255.0 * np.nan_to_num(att[..., 3:4])
    bg = np.full((size, size, 3), 20.0, np.float32) if background is None else background
    img = np.where(mask[..., None], img, bg)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8), mask


def _background(rng: np.random.Generator, size: int) -> np.ndarray:
    kind = rng.integers(0, 3)
    if kind == 0:                        # synth's dark constant background
        return np.full((size, size, 3), 20.0, np.float32)
    col = rng.uniform(0, 120, 3).astype(np.float32)
    if kind == 1:
        return np.broadcast_to(col, (size, size, 3)).copy()
    return np.clip(col + 25 * _noise(rng, size, 8, 3), 0, 255)


def make_dataset(cfg: HDMDataConfig) -> dict[str, np.ndarray]:
    """Render ``cfg.samples`` samples of ``cfg.split``.  Returns images (N, s, s, 3) uint8 at the
    stored size s, masks (N, s, s) uint8 (1 on the surface), grids (N, GRID, GRID, 3) float32
    (camera frame, metres), texture / light indices into TEXTURES / LIGHTS, the family index,
    amplitude and the pose (N, 4, 4).  Deterministic for a config."""
    cfg.validate()
    rng = np.random.default_rng([cfg.seed, _SPLIT_SEED[cfg.split], 0x4D])
    tex_fams = HELDOUT_TEXTURES if cfg.split == 'heldout-texture' else TRAIN_TEXTURES
    lights = HELDOUT_LIGHTS if cfg.split == 'heldout-light' else TRAIN_LIGHTS
    # texture instances: training ones from seeds [0, n), test ones from [1000, 1000 + n)
    base = 0 if cfg.split == 'train' else 1000
    bank: dict[tuple[str, int], np.ndarray] = {}
    N, size, s = cfg.samples, H.INPUT_SIZE, cfg.stored
    out = {'images': np.empty((N, s, s, 3), np.uint8), 'masks': np.empty((N, s, s), np.uint8),
           'grids': np.empty((N, H.GRID, H.GRID, 3), np.float32),
           'texture': np.empty(N, np.int16), 'light': np.empty(N, np.int16),
           'family': np.empty(N, np.int16), 'amplitude': np.empty(N, np.float32),
           'pose': np.empty((N, 4, 4), np.float32)}
    f0 = H.CANON_FOCAL
    for i in range(N):
        # the even split keeps its original draw, so that its datasets (and the records of
        # models trained on them) stay reproducible
        fam = FAMILIES[int(rng.integers(0, 2)) if cfg.wave_fraction == 0.5
                       else int(rng.random() < cfg.wave_fraction)]
        amp = float(rng.uniform(0, cfg.max_amplitude)) if fam == 'bend' else \
            float(rng.uniform(0, min(cfg.max_amplitude, 1.5)))
        X = sheet_grid(fam, float(rng.uniform(0, 30)), amp, rng.uniform(0, 2 * np.pi, 3))
        fill = rng.uniform(*cfg.fill)
        dist = f0 * synth.EXTENT['sheet'] / (fill * size)
        yaw, pitch, roll = np.radians(rng.uniform(-1, 1, 3) * [cfg.max_yaw_deg,
                                                              cfg.max_pitch_deg,
                                                              cfg.max_roll_deg])
        T = pose(yaw, pitch, roll, dist, np.r_[rng.uniform(-0.06, 0.06, 2), 0.0])
        Xc = X.reshape(-1, 3) @ T[:3, :3].T + T[:3, 3]
        tf = tex_fams[int(rng.integers(0, len(tex_fams)))]
        key = (tf, base + int(rng.integers(0, cfg.textures_per_family)))
        if key not in bank:
            bank[key] = texture(*key)
        tex = bank[key]
        if rng.random() < 0.5:                                    # mirrored / rotated uses
            tex = np.ascontiguousarray(np.rot90(tex, int(rng.integers(1, 4))))
        light = lights[int(rng.integers(0, len(lights)))]
        img, mask = render(Xc.reshape(H.GRID, H.GRID, 3), tex, light, size,
                           _background(rng, size),
                           specular=0.6 if tf == 'endoscopy' else 0.0)
        img = img.astype(np.float32) * rng.uniform(0.85, 1.15)
        if cfg.noise > 0:
            img += rng.normal(0, rng.uniform(0, cfg.noise), img.shape)
        img = np.clip(np.rint(img), 0, 255).astype(np.uint8)
        out['images'][i] = cv2.resize(img, (s, s), interpolation=cv2.INTER_AREA)
        out['masks'][i] = cv2.resize(mask.astype(np.float32), (s, s),
                                     interpolation=cv2.INTER_AREA) > 0.5
        out['grids'][i] = Xc.reshape(H.GRID, H.GRID, 3)
        out['texture'][i] = TEXTURES.index(tf)
        out['light'][i] = list(LIGHTS).index(light)
        out['family'][i] = FAMILIES.index(fam)
        out['amplitude'][i] = amp
        out['pose'][i] = T
    return out
