"""Deterministic synthetic sequences with ground truth: a deforming textured surface (waving
flag, face-like cap, isometrically bending sheet, breathing sphere cap or peristaltic tube)
seen by a moving pinhole camera, optionally with an opaque textured occluder sweeping across
between camera and surface and a textured wall behind it (still in the world: its image moves
with the camera only).

Per frame: an rgb8 image rendered by a vectorised triangle rasteriser (z-buffer, bilinear texture,
Lambertian shading), a depth image (32FC1 metres, NaN off the surface and the occluder, the
wall's depth where it is seen),
CameraInfo intrinsics, the camera pose, and for every tracked reference pixel its ground-truth 3D
point in the camera optical frame (x right, y down, z forward; metres), its 2D track and its
visibility (0 out of the image, self-occluded or behind the occluder).

Track ids are the reference pixels' linear indices ``y * width + x`` (the tracker uses the same
convention), sampled every ``stride`` pixels.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ._raster_kernel import zbuffer

SURFACES = ('flag', 'face', 'sheet', 'sphere', 'tube')
SPHERE_RADIUS = 0.3                   # sphere cap: rest radius (m) and polar half-angle
SPHERE_HALF_ANGLE = np.radians(70.0)  # a 140 deg arc of the sphere
TUBE_RADIUS = 0.2                     # tube: rest radius (m), length (m) and the half-angle of
TUBE_LENGTH = 0.9                     # the arc round its axis that faces the camera
TUBE_HALF_ANGLE = np.radians(70.0)
# object width (m) the focal length is set for: the surface fills ~75% of the image width
EXTENT = {'flag': 1.0, 'face': 0.5, 'sheet': 1.0,
          'sphere': 2 * SPHERE_RADIUS * float(np.sin(SPHERE_HALF_ANGLE)), 'tube': TUBE_LENGTH}
MIN_DISTANCE = 1.5                    # m: every surface (and the occluder) in front of the camera
MAX_AMPLITUDE = 4.0
OCCLUDER_AREA = 0.3                   # occluder disc area / the surface's area in frame 0
BACKGROUND_BEHIND = 0.5               # the wall's distance behind the surface / camera distance


@dataclass(frozen=True)
class SynthConfig:
    surface: str = 'flag'
    width: int = 256
    height: int = 192
    frames: int = 60
    fps: float = 10.0
    seed: int = 0
    distance: float = 4.0       # camera distance to the object centre, metres
    stride: int = 2             # ground-truth track sampling on the reference pixel grid
    noise: float = 0.0          # image noise sigma (intensity units)
    camera_motion_deg: float = 12.0
    amplitude: float = 1.0      # deformation amplitude multiplier (0: rigid)
    occluder: bool = False      # a textured disc sweeps across in front of the surface
    background: bool = False    # a textured wall behind the surface, still in the world
    # periodic deformation (0: off): the surface's time runs forwards and back over
    # period_frames / fps seconds, tau(f) = T (1 - cos(2 pi f / period_frames)) / 2, so every
    # state recurs (twice a period, breathing-like) while the camera keeps moving
    period_frames: int = 0
    start_ns: int = 1_700_000_000 * 1_000_000_000

    def validate(self) -> None:
        if self.surface not in SURFACES:
            raise ValueError(f'surface={self.surface!r}: expected one of {SURFACES}')
        if not (64 <= self.width <= 1920 and 48 <= self.height <= 1080):
            raise ValueError(f'width x height = {self.width}x{self.height}: expected 64..1920 x '
                             '48..1080')
        if not 3 <= self.frames <= 2000:
            raise ValueError(f'frames={self.frames}: expected 3..2000')
        if not self.fps > 0:
            raise ValueError(f'fps={self.fps}: expected > 0')
        if self.stride < 1:
            raise ValueError(f'stride={self.stride}: expected >= 1')
        if not self.distance >= MIN_DISTANCE:
            raise ValueError(f'distance={self.distance}: expected >= {MIN_DISTANCE} m (the '
                             'surface must stay in front of the camera)')
        if not self.noise >= 0:
            raise ValueError(f'noise={self.noise}: expected >= 0')
        if not 0 <= self.camera_motion_deg <= 90:
            raise ValueError(f'camera_motion_deg={self.camera_motion_deg}: expected 0..90')
        if not 0 <= self.amplitude <= MAX_AMPLITUDE:
            raise ValueError(f'amplitude={self.amplitude}: expected 0..{MAX_AMPLITUDE}')
        if not isinstance(self.occluder, (bool, np.bool_)):
            raise ValueError(f'occluder={self.occluder!r}: expected True or False')
        if not isinstance(self.background, (bool, np.bool_)):
            raise ValueError(f'background={self.background!r}: expected True or False')
        _check_period(self.period_frames)


def _check_period(period_frames: int) -> None:
    if isinstance(period_frames, (bool, np.bool_)) or not isinstance(
            period_frames, (int, np.integer)) or not (period_frames == 0 or period_frames >= 4):
        raise ValueError(f'period_frames={period_frames!r}: expected 0 (off) or an integer '
                         '>= 4 (frames per period of the deformation)')


def deformation_time(f: int, fps: float, period_frames: int = 0) -> float:
    """The surface's time (s) at frame f: f / fps, or with ``period_frames`` > 0 the periodic
    sweep T (1 - cos(2 pi f / period_frames)) / 2 with T = period_frames / fps (the states of
    [0, T] forwards, then back: frames f and f + period_frames, and f and period_frames - f,
    deform identically)."""
    if not period_frames:
        return f / fps
    return period_frames / fps * 0.5 * (1.0 - float(np.cos(2 * np.pi * f / period_frames)))


@dataclass
class SynthSequence:
    config: SynthConfig
    images: np.ndarray          # (F, H, W, 3) uint8 rgb
    depth: np.ndarray           # (F, H, W) float32 metres, NaN where no surface
    K: np.ndarray               # (3, 3)
    T_camera_world: np.ndarray  # (F, 4, 4)
    stamps_ns: np.ndarray       # (F,) int64
    track_ids: np.ndarray       # (P,) uint32
    W: np.ndarray               # (2F, P) ground-truth tracks, pixels
    V: np.ndarray               # (F, P) ground-truth visibility
    S: np.ndarray               # (F, P, 3) ground truth, camera optical frame, metres
    S_world: np.ndarray         # (F, P, 3) ground truth, world (object) frame
    occluder: np.ndarray | None = None  # (F, 4) disc centre u, v (px), radius (px), depth (m)
    # (F, H, W, 2) float32: the surface coordinates (s, t) seen at each pixel, NaN off the
    # surface and behind the occluder (not saved in the npz); with ``phase`` (the deformation's
    # random phases) they give the truth of any pixel of any frame: ``pixel_truth``
    surface_st: np.ndarray | None = None
    phase: np.ndarray | None = None

    def npz_dict(self) -> dict[str, np.ndarray]:
        c = self.config
        d = {'images': self.images, 'depth': self.depth, 'K': self.K,
             'T_camera_world': self.T_camera_world, 'stamps_ns': self.stamps_ns,
             'track_ids': self.track_ids, 'W': self.W, 'V': self.V, 'S': self.S,
             'S_world': self.S_world, 'surface': np.array(c.surface), 'fps': np.array(c.fps),
             'seed': np.array(c.seed), 'distance': np.array(c.distance),
             'noise': np.array(c.noise), 'camera_motion_deg': np.array(c.camera_motion_deg),
             'amplitude': np.array(c.amplitude), 'occluder_on': np.array(bool(c.occluder)),
             'background_on': np.array(bool(c.background))}
        if c.period_frames:
            d['period_frames'] = np.array(c.period_frames)
        if self.occluder is not None:
            d['occluder'] = self.occluder
        return d


# ---------------------------------------------------------------- surfaces (object frame)

def _surface(kind: str, s: np.ndarray, t: np.ndarray, tau: float, amp: float,
             phase: np.ndarray) -> np.ndarray:
    """3D points (N, 3) of the surface at parameters s, t in [0, 1] and time tau (seconds).
    Object frame: x right, y down, z away from the camera (the camera starts on -z)."""
    if kind == 'sheet':
        return _sheet(s, t, tau, amp, phase)
    if kind == 'sphere':
        return _sphere(s, t, tau, amp, phase)
    if kind == 'tube':
        return _tube(s, t, tau, amp, phase)
    if kind == 'flag':
        x = (s - 0.5) * 1.0
        y = (t - 0.5) * 0.7
        wave = np.sin(2 * np.pi * (1.1 * s - 0.45 * tau) + 1.3 * t + phase[0])
        wave2 = np.sin(2 * np.pi * (0.6 * t + 0.35 * tau) + 2.0 * s + phase[1])
        z = amp * s * (0.09 * wave + 0.03 * wave2)
        # the free end also sags and sways a little in-plane
        x = x - amp * 0.02 * s ** 2 * (1 + np.cos(2 * np.pi * 0.3 * tau))
        y = y + amp * 0.015 * s ** 2 * np.sin(2 * np.pi * 0.4 * tau + phase[2])
        return np.stack([x, y, z], axis=1)
    # face-like: an elliptic cap with nose, eye sockets, cheeks and a jaw that opens
    x = (s - 0.5) * 0.36
    y = (t - 0.5) * 0.48
    r2 = (x / 0.18) ** 2 + (y / 0.24) ** 2
    cap = 0.12 * np.sqrt(np.clip(1.0 - r2, 0.0, 1.0))
    nose = 0.05 * np.exp(-((x / 0.025) ** 2 + ((y + 0.01) / 0.05) ** 2))
    eyes = -0.018 * (np.exp(-(((x - 0.07) / 0.03) ** 2 + ((y + 0.07) / 0.02) ** 2))
                     + np.exp(-(((x + 0.07) / 0.03) ** 2 + ((y + 0.07) / 0.02) ** 2)))
    open_ = amp * 0.5 * (1 - np.cos(2 * np.pi * 0.35 * tau + phase[0]))
    jaw = np.clip((y - 0.05) / 0.19, 0.0, 1.0)
    puff = amp * 0.012 * np.sin(2 * np.pi * 0.5 * tau + phase[1]) * (
        np.exp(-(((x - 0.09) / 0.04) ** 2 + ((y - 0.04) / 0.04) ** 2))
        + np.exp(-(((x + 0.09) / 0.04) ** 2 + ((y - 0.04) / 0.04) ** 2)))
    z = -(cap + nose + eyes + puff) + 0.03 * open_ * jaw
    y = y + 0.035 * open_ * jaw
    return np.stack([x, y, z], axis=1)


def _sheet(s: np.ndarray, t: np.ndarray, tau: float, amp: float,
           phase: np.ndarray) -> np.ndarray:
    """A 1.0 x 0.7 m sheet bent isometrically into a cylinder of curvature k(tau) about an axis
    in its plane through its centre whose direction alpha(tau) turns slowly: the arc length a
    across the axis is kept exactly (x_a = sin(k a) / k, z = (1 - cos(k a)) / k, through sinc
    so that k -> 0 is the flat sheet).  k swings between -1.4 amp and 1.4 amp rad/m."""
    u = (s - 0.5) * 1.0
    v = (t - 0.5) * 0.7
    k = amp * 1.4 * np.sin(2 * np.pi * 0.12 * tau + phase[0])
    alpha = 0.4 * np.sin(2 * np.pi * 0.07 * tau + phase[1])
    ca, sa = np.cos(alpha), np.sin(alpha)
    a = u * ca + v * sa                    # arc length across the bending axis
    b = -u * sa + v * ca                   # along the axis (unchanged)
    xa = a * np.sinc(k * a / np.pi)                              # sin(k a) / k
    z = 0.5 * k * a ** 2 * np.sinc(k * a / (2 * np.pi)) ** 2     # (1 - cos(k a)) / k
    z = z - 0.25 * k * 0.25 * np.sinc(k * 0.5 / (2 * np.pi)) ** 2  # half the edge sagitta
    return np.stack([xa * ca - b * sa, xa * sa + b * ca, z], axis=1)


# bump directions on the sphere cap: (polar, azimuth) in degrees, height (m), angular width
_SPHERE_BUMPS = np.array([[35.0, 20.0, 0.030, 0.30], [50.0, 150.0, 0.025, 0.25],
                          [42.0, 260.0, 0.028, 0.28], [12.0, 95.0, 0.018, 0.22]])


def _unit(polar: np.ndarray | float, azimuth: np.ndarray | float) -> np.ndarray:
    """Unit vectors (..., 3) at polar angle from -z (towards the camera) and azimuth."""
    sp = np.sin(polar)
    return np.stack([sp * np.cos(azimuth), sp * np.sin(azimuth), -np.cos(polar)], axis=-1)


def _sphere(s: np.ndarray, t: np.ndarray, tau: float, amp: float,
            phase: np.ndarray) -> np.ndarray:
    """A 140 deg cap of a 0.3 m sphere facing the camera (apex towards -z), organ-like: four
    smooth bumps that pulse, a bulge travelling round the cap and a breathing radius, all
    scaled by amp (amp = 0: a rigid bumpy cap).  The disc domain of (s, t) maps to the polar
    angle linearly in its radius (an azimuthal equidistant chart)."""
    u, v = (s - 0.5) / 0.5, (t - 0.5) / 0.5
    rho = np.hypot(u, v)
    theta = rho * SPHERE_HALF_ANGLE
    g = SPHERE_HALF_ANGLE * np.sinc(theta / np.pi)          # sin(theta) / rho
    d = np.stack([u * g, v * g, -np.cos(theta)], axis=1)   # unit directions
    cb = _unit(np.radians(_SPHERE_BUMPS[:, 0]), np.radians(_SPHERE_BUMPS[:, 1]))  # (4, 3)
    pulse = 1 + amp * 0.5 * np.sin(2 * np.pi * np.array([0.21, 0.17, 0.26, 0.3]) * tau
                                   + phase[1] + 2.1 * np.arange(4))
    bumps = np.exp(-(1 - d @ cb.T) / _SPHERE_BUMPS[:, 3] ** 2) @ (_SPHERE_BUMPS[:, 2] * pulse)
    cm = _unit(np.radians(45.0), 2 * np.pi * 0.08 * tau + phase[2])
    bulge = amp * 0.035 * np.exp(-(1 - d @ cm) / 0.3 ** 2)
    r = SPHERE_RADIUS * (1 + amp * 0.06 * np.sin(2 * np.pi * 0.2 * tau + phase[0])) + bumps \
        + bulge
    centre_z = SPHERE_RADIUS * (1 + np.cos(SPHERE_HALF_ANGLE)) / 2  # apex and rim at -/+ z
    return r[:, None] * d + [0.0, 0.0, centre_z]


def _tube(s: np.ndarray, t: np.ndarray, tau: float, amp: float,
          phase: np.ndarray) -> np.ndarray:
    """A bowel-like tube: the 140 deg of a 0.2 m radius, 0.9 m long cylinder about the x axis
    that face the camera, with a peristaltic wave (the radius +-12% amp) travelling along it
    and the axis bending slowly in the y-z plane (amp 0: a rigid half-tube).  s runs along the
    axis, t round it."""
    x = (s - 0.5) * TUBE_LENGTH
    theta = (t - 0.5) * 2 * TUBE_HALF_ANGLE
    wave = np.sin(2 * np.pi * (1.2 * s - 0.35 * tau) + phase[0])
    r = TUBE_RADIUS * (1 + amp * 0.12 * wave)
    bend = amp * 0.04 * np.sin(2 * np.pi * 0.15 * tau + phase[1]) * (2 * s - 1) ** 2
    centre_z = TUBE_RADIUS * (1 + np.cos(TUBE_HALF_ANGLE)) / 2   # the crest and rims at -/+ z
    return np.stack([x, r * np.sin(theta) + 0.5 * bend, -r * np.cos(theta) + centre_z + bend],
                    axis=1)


def _in_domain(kind: str, s: np.ndarray, t: np.ndarray) -> np.ndarray:
    if kind in ('flag', 'sheet', 'tube'):
        return np.ones_like(s, dtype=bool)
    return ((s - 0.5) / 0.5) ** 2 + ((t - 0.5) / 0.5) ** 2 <= 0.98


def _texture(rng: np.random.Generator, size: int = 512) -> np.ndarray:
    """Multi-scale random texture (size, size, 3) uint8: trackable at every scale."""
    tex = np.zeros((size, size, 3), np.float32)
    for scale, weight in ((4, 0.5), (16, 0.8), (48, 1.0), (128, 0.7)):
        noise = rng.normal(size=(scale, scale, 3)).astype(np.float32)
        tex += weight * cv2.resize(noise, (size, size), interpolation=cv2.INTER_CUBIC)
    # blobs of saturated colour
    for _ in range(60):
        c = (int(rng.integers(0, size)), int(rng.integers(0, size)))
        r = int(rng.integers(4, 18))
        col = tuple(float(v) for v in rng.uniform(-2.5, 2.5, 3))
        cv2.circle(tex, c, r, col, -1, lineType=cv2.LINE_AA)
    tex = (tex - tex.mean()) / (tex.std() + 1e-6)
    return np.clip(128 + 45 * tex, 10, 245).astype(np.uint8)


def _occluder_texture(rng: np.random.Generator, size: int = 256) -> np.ndarray:
    """The occluder's texture (size, size, 3) uint8: bold diagonal stripes in a cool tint over
    fine noise, unlike the surface's blobs, so that it is trackable but never confused."""
    y, x = np.mgrid[0:size, 0:size].astype(np.float32)
    stripes = (np.sin(2 * np.pi * (x + y) / 24.0) > 0).astype(np.float32)
    fine = cv2.resize(rng.normal(size=(64, 64, 3)).astype(np.float32), (size, size),
                      interpolation=cv2.INTER_CUBIC)
    tint = np.array([70.0, 110.0, 190.0], np.float32)
    tex = tint * (0.45 + 0.55 * stripes[..., None]) + 18.0 * fine
    return np.clip(tex, 10, 245).astype(np.uint8)


def _occluder_path(cfg: SynthConfig, area_px: float, rng: np.random.Generator) -> np.ndarray:
    """(F, 4): the occluder disc's image centre u, v (px), radius (px) and depth (m, camera
    frame) per frame.  A fronto-parallel disc of OCCLUDER_AREA x ``area_px`` (the surface's
    area in frame 0) at half the camera distance, entering from one side just outside the image
    in frame 0 and leaving at the other in the last frame, on a slightly sloped line."""
    F, W, H = cfg.frames, cfg.width, cfg.height
    r = max(np.sqrt(OCCLUDER_AREA * area_px / np.pi), 1.0)
    side = 1.0 if rng.random() < 0.5 else -1.0
    v0, slope = H * (0.5 + rng.uniform(-0.12, 0.12)), H * rng.uniform(-0.1, 0.1)
    a = np.arange(F) / (F - 1)
    u = (W - 1) / 2 + side * (a - 0.5) * (W + 2 * r + 4)
    v = v0 + slope * (a - 0.5)
    return np.stack([u, v, np.full(F, r), np.full(F, 0.5 * cfg.distance)], axis=1)


def _wall(cfg: SynthConfig, K: np.ndarray, T_cw: np.ndarray, texture: np.ndarray
          ) -> tuple[np.ndarray, np.ndarray]:
    """The background wall seen by the camera T_cw: its image (H, W, 3) float32 and its depth
    (H, W) m (camera z).  A plane at world z = BACKGROUND_BEHIND x distance, behind the
    surface and facing the cameras, its texture repeating every ``EXTENT`` metres (about the
    surface's own texture density), lit evenly."""
    H, Wd = cfg.height, cfg.width
    xs, ys = np.meshgrid(np.arange(Wd, dtype=np.float64), np.arange(H, dtype=np.float64))
    d_c = np.stack([(xs - K[0, 2]) / K[0, 0], (ys - K[1, 2]) / K[1, 1], np.ones_like(xs)], -1)
    R, t = T_cw[:3, :3], T_cw[:3, 3]
    centre = -R.T @ t
    d_w = d_c @ R                                   # R^T d_c per pixel
    depth = (BACKGROUND_BEHIND * cfg.distance - centre[2]) / d_w[..., 2]
    P = centre + depth[..., None] * d_w
    n = texture.shape[0]
    scale = n / EXTENT[cfg.surface]
    img = cv2.remap(texture, np.mod(P[..., 0] * scale, n).astype(np.float32),
                    np.mod(P[..., 1] * scale, n).astype(np.float32), cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_WRAP)
    return 0.8 * img.astype(np.float32), depth


def _occluded(uv: np.ndarray, disc: np.ndarray) -> np.ndarray:
    """Which image points uv (N, 2) the occluder disc (u, v, radius, depth) covers."""
    return np.hypot(uv[:, 0] - disc[0], uv[:, 1] - disc[1]) <= disc[2]


# ---------------------------------------------------------------- camera

def _look_at(centre: np.ndarray, target: np.ndarray) -> np.ndarray:
    """T_camera_world for an optical frame at ``centre`` looking at ``target`` (y down)."""
    z = target - centre
    z /= np.linalg.norm(z)
    up = np.array([0.0, -1.0, 0.0])  # world y is down in the image, so camera -y is "up"
    x = np.cross(up, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = -R @ centre
    return T


def _camera_poses(cfg: SynthConfig, rng: np.random.Generator) -> np.ndarray:
    F = cfg.frames
    tau = np.arange(F) / cfg.fps
    a = np.radians(cfg.camera_motion_deg)
    ph = rng.uniform(0, 2 * np.pi, 2)
    yaw = a * np.sin(2 * np.pi * 0.12 * tau + ph[0])
    pitch = 0.5 * a * np.sin(2 * np.pi * 0.09 * tau + ph[1])
    poses = np.empty((F, 4, 4))
    for f in range(F):
        c = cfg.distance * np.array([np.sin(yaw[f]) * np.cos(pitch[f]), np.sin(pitch[f]),
                                     -np.cos(yaw[f]) * np.cos(pitch[f])])
        poses[f] = _look_at(c, np.zeros(3))
    return poses


# ---------------------------------------------------------------- rasteriser

def _grid_mesh(kind: str, n_s: int, n_t: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    s, t = np.meshgrid(np.linspace(0, 1, n_s), np.linspace(0, 1, n_t))
    s, t = s.ravel(), t.ravel()
    i = np.arange(n_s * n_t).reshape(n_t, n_s)
    a, b, c, d = i[:-1, :-1].ravel(), i[:-1, 1:].ravel(), i[1:, :-1].ravel(), i[1:, 1:].ravel()
    tris = np.concatenate([np.stack([a, b, c], 1), np.stack([b, d, c], 1)])
    inside = _in_domain(kind, s, t)
    tris = tris[inside[tris].all(axis=1)]
    return s, t, tris


def rasterise(uv: np.ndarray, depth: np.ndarray, attrs: np.ndarray, tris: np.ndarray,
              width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Z-buffered rasterisation of triangles with per-vertex attributes.

    uv (N, 2) pixel coordinates of vertices, depth (N,), attrs (N, A).  Returns the depth buffer
    (H, W) (inf where empty) and interpolated attributes (H, W, A) (NaN where empty).  Pixel
    centres are at integer coordinates.
    """
    p = np.ascontiguousarray(uv[tris], np.float64)              # T x 3 x 2
    zbuf = np.full(height * width, np.inf)
    winner = np.full(height * width, -1, np.int64)
    weights = np.zeros((height * width, 3))
    zbuffer(p, np.ascontiguousarray(depth, np.float64), np.ascontiguousarray(tris, np.int64),
            width, height, zbuf, winner, weights)
    hit = np.nonzero(winner >= 0)[0]
    out = np.full((height * width, attrs.shape[1]), np.nan)
    out[hit] = np.einsum('nk,nka->na', weights[hit], attrs[tris[winner[hit]]])
    return zbuf.reshape(height, width), out.reshape(height, width, attrs.shape[1])


def _project(K: np.ndarray, Xc: np.ndarray) -> np.ndarray:
    return (Xc[:, :2] / Xc[:, 2:3]) * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]


def generate(cfg: SynthConfig) -> SynthSequence:
    """Render the sequence and its ground truth (deterministic for a given config)."""
    cfg.validate()
    rng = np.random.default_rng(cfg.seed)
    texture = _texture(rng)
    phase = rng.uniform(0, 2 * np.pi, 3)
    f = 0.75 * cfg.width * cfg.distance / EXTENT[cfg.surface]
    K = np.array([[f, 0, (cfg.width - 1) / 2], [0, f, (cfg.height - 1) / 2], [0, 0, 1.0]])
    poses = _camera_poses(cfg, rng)
    n_s = max(40, cfg.width // 3)
    s, t, tris = _grid_mesh(cfg.surface, n_s, int(n_s * 0.75))
    F, H, Wd = cfg.frames, cfg.height, cfg.width
    light = np.array([0.3, -0.4, -1.0])
    light /= np.linalg.norm(light)
    images = np.empty((F, H, Wd, 3), np.uint8)
    depth = np.empty((F, H, Wd), np.float32)
    surface_st = np.empty((F, H, Wd, 2), np.float32)
    zbufs = []
    ref_st = None
    occ_rng = np.random.default_rng([cfg.seed, 0x0CC])  # apart from rng: defaults unchanged
    occ_tex = _occluder_texture(occ_rng) if cfg.occluder else None
    occ = None
    wall_tex = _texture(np.random.default_rng([cfg.seed, 0xBAC])) if cfg.background else None
    pix = np.stack(np.meshgrid(np.arange(Wd), np.arange(H)), axis=-1).reshape(-1, 2) \
        if cfg.occluder else np.empty((0, 2))
    for fi in range(F):
        tau = deformation_time(fi, cfg.fps, cfg.period_frames)
        Xw = _surface(cfg.surface, s, t, tau, cfg.amplitude, phase)
        Xc = Xw @ poses[fi, :3, :3].T + poses[fi, :3, 3]
        uv = _project(K, Xc)
        normals = _vertex_normals(Xc, tris)
        shade = 0.35 + 0.65 * np.abs(normals @ light)
        attrs = np.stack([s, t, shade], axis=1)
        zbuf, att = rasterise(uv, Xc[:, 2], attrs, tris, Wd, H)
        covered = np.isfinite(zbuf)
        surface_st[fi] = att[..., :2]
        st = np.nan_to_num(att[..., :2])
        tex = cv2.remap(texture, (st[..., 0] * (texture.shape[1] - 1)).astype(np.float32),
                        (st[..., 1] * (texture.shape[0] - 1)).astype(np.float32),
                        cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
        img = tex.astype(np.float32) * np.nan_to_num(att[..., 2:3])
        img[~covered] = 20.0
        wall_depth = None
        if wall_tex is not None:
            wall, wall_depth = _wall(cfg, K, poses[fi], wall_tex)
            img[~covered] = wall[~covered]
        if occ_tex is not None:
            if occ is None:
                occ = _occluder_path(cfg, float(covered.sum()), occ_rng)
            disc = occ[fi]
            on = _occluded(pix, disc).reshape(H, Wd) & (disc[3] < zbuf)
            ys, xs = np.nonzero(on)
            n = occ_tex.shape[0] - 1
            tu = np.clip((xs - disc[0] + disc[2]) / (2 * disc[2]) * n, 0, n)
            tv = np.clip((ys - disc[1] + disc[2]) / (2 * disc[2]) * n, 0, n)
            img[ys, xs] = occ_tex[np.rint(tv).astype(int), np.rint(tu).astype(int)]
            zbuf = np.where(on, disc[3], zbuf)
            covered = covered | on
            surface_st[fi][on] = np.nan
        if cfg.noise > 0:
            img += rng.normal(0, cfg.noise, img.shape)
        images[fi] = np.clip(np.rint(img), 0, 255).astype(np.uint8)
        depth[fi] = np.where(covered, zbuf, np.nan if wall_depth is None else wall_depth
                             ).astype(np.float32)
        zbufs.append(zbuf)  # with the occluder's depth: V is 0 for points behind it
        if fi == 0:
            ref_st = att[..., :2]
    assert ref_st is not None
    # ground-truth tracks of every stride-th covered reference pixel
    grid = np.zeros((H, Wd), bool)
    grid[::cfg.stride, ::cfg.stride] = True
    ys, xs = np.nonzero(np.isfinite(zbufs[0]) & grid)
    ids = (ys * Wd + xs).astype(np.uint32)
    ps, pt = ref_st[ys, xs, 0], ref_st[ys, xs, 1]
    P = ids.size
    Wt = np.empty((2 * F, P))
    V = np.empty((F, P))
    S = np.empty((F, P, 3))
    Sw = np.empty((F, P, 3))
    for fi in range(F):
        Xw = _surface(cfg.surface, ps, pt, deformation_time(fi, cfg.fps, cfg.period_frames),
                      cfg.amplitude, phase)
        Xc = Xw @ poses[fi, :3, :3].T + poses[fi, :3, 3]
        uv = _project(K, Xc)
        Wt[2 * fi], Wt[2 * fi + 1] = uv[:, 0], uv[:, 1]
        S[fi], Sw[fi] = Xc, Xw
        xi = np.clip(np.rint(uv[:, 0]).astype(int), 0, Wd - 1)
        yi = np.clip(np.rint(uv[:, 1]).astype(int), 0, H - 1)
        inside = (uv[:, 0] >= 0) & (uv[:, 0] <= Wd - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= H - 1)
        V[fi] = inside & (Xc[:, 2] <= zbufs[fi][yi, xi] + 0.02)
    stamps = cfg.start_ns + np.rint(np.arange(F) / cfg.fps * 1e9).astype(np.int64)
    return SynthSequence(config=cfg, images=images, depth=depth, K=K, T_camera_world=poses,
                         stamps_ns=stamps, track_ids=ids, W=Wt, V=V, S=S, S_world=Sw,
                         occluder=occ, surface_st=surface_st, phase=phase)


def pixel_truth(seq: SynthSequence, frame: int, xy: np.ndarray) -> np.ndarray:
    """(F, n, 3): the ground truth (camera optical frame, metres) over the whole sequence of
    the surface points seen at the integer pixels ``xy`` (n, 2) of ``frame`` -- a tracker's
    track started there -- NaN where that pixel sees no surface (off it, or the occluder)."""
    if seq.surface_st is None or seq.phase is None:
        raise ValueError('pixel_truth: the sequence has no surface_st (loaded from an npz?)')
    cfg = seq.config
    F, H, Wd = seq.surface_st.shape[:3]
    if not 0 <= frame < F:
        raise ValueError(f'pixel_truth: frame={frame} outside 0..{F - 1}')
    xy = np.asarray(xy, np.intp).reshape(-1, 2)
    if xy.size and ((xy < 0).any() or (xy[:, 0] >= Wd).any() or (xy[:, 1] >= H).any()):
        raise ValueError(f'pixel_truth: pixels outside the {Wd}x{H} image')
    st = seq.surface_st[frame, xy[:, 1], xy[:, 0]].astype(np.float64)
    ok = np.isfinite(st).all(axis=1)
    out = np.full((F, xy.shape[0], 3), np.nan)
    for fi in range(F):
        Xw = _surface(cfg.surface, st[ok, 0], st[ok, 1],
                      deformation_time(fi, cfg.fps, cfg.period_frames), cfg.amplitude,
                      seq.phase)
        out[fi, ok] = Xw @ seq.T_camera_world[fi, :3, :3].T + seq.T_camera_world[fi, :3, 3]
    return out


def _vertex_normals(X: np.ndarray, tris: np.ndarray) -> np.ndarray:
    n = np.cross(X[tris[:, 1]] - X[tris[:, 0]], X[tris[:, 2]] - X[tris[:, 0]])
    vn = np.zeros_like(X)
    for k in range(3):
        np.add.at(vn, tris[:, k], n)
    return vn / np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-12)


def scene_flow_ground_truth(seq: SynthSequence, f: int) -> np.ndarray:
    """True 3D velocity (P, 3, m/s) of the tracked points between frames f-1 and f in the
    object frame of ``core.sceneflow.definition``: the camera's own motion removed, in the
    axes of the earlier camera f-1, ``R_{f-1} (X_world_f - X_world_{f-1}) * fps``."""
    if not 1 <= f < seq.S.shape[0]:
        raise ValueError(f'f: expected 1..{seq.S.shape[0] - 1}, got {f}')
    R = seq.T_camera_world[f - 1, :3, :3]
    return (seq.S_world[f] - seq.S_world[f - 1]) @ R.T * seq.config.fps


def dense_tracks(surface: str = 'flag', frames: int = 60, points: int = 10000,
                 projection: str = 'orthographic', camera_motion_deg: float = 40.0,
                 fps: float = 10.0, distance: float = 4.0, focal: float = 2000.0,
                 seed: int = 0, sampling: str = 'random',
                 amplitude: float = 1.0, period_frames: int = 0) -> dict[str, np.ndarray]:
    """Ground-truth dense tracks of a deforming surface without rendering (for NRSfM benchmarks
    at any size): ``points`` surface samples, the same camera path as ``generate``.
    ``sampling``: 'random' (uniform in the surface's domain) or 'grid' (a regular grid of the
    domain, about ``points`` samples, as a tracker's every-stride-th pixel gives).
    ``amplitude``: the deformation multiplier of ``SynthConfig`` (0: rigid).
    ``period_frames``: periodic deformation as ``SynthConfig`` (0: off; the camera still moves).

    ``projection``: 'orthographic' (W = focal / distance x the camera-frame x, y) or
    'weak-perspective' (W = focal / mean depth of the frame x x, y).  Returns W (2F, P),
    V (F, P) ones, S (F, P, 3) camera frame and S_world (F, P, 3), metres."""
    if surface not in SURFACES:
        raise ValueError(f'surface={surface!r}: expected one of {SURFACES}')
    if projection not in ('orthographic', 'weak-perspective'):
        raise ValueError(f"projection={projection!r}: expected 'orthographic' or "
                         "'weak-perspective'")
    if frames < 3 or points < 3:
        raise ValueError(f'frames={frames}, points={points}: expected >= 3')
    if sampling not in ('random', 'grid'):
        raise ValueError(f"sampling={sampling!r}: expected 'random' or 'grid'")
    if not 0 <= amplitude <= MAX_AMPLITUDE:
        raise ValueError(f'amplitude={amplitude}: expected 0..{MAX_AMPLITUDE}')
    _check_period(period_frames)
    rng = np.random.default_rng(seed)
    phase = rng.uniform(0, 2 * np.pi, 3)
    cfg = SynthConfig(surface=surface, frames=frames, fps=fps, seed=seed, distance=distance,
                      camera_motion_deg=camera_motion_deg, amplitude=amplitude)
    poses = _camera_poses(cfg, rng)
    if sampling == 'grid':                   # the domain's share of the unit square, then a grid
        cs, ct = rng.uniform(0, 1, (2, 20000))
        n = int(np.ceil(np.sqrt(points / max(_in_domain(surface, cs, ct).mean(), 1e-3))))
        s, t = (a.ravel() for a in np.meshgrid((np.arange(n) + 0.5) / n,
                                               (np.arange(n) + 0.5) / n))
        keep = _in_domain(surface, s, t)
        s, t = s[keep], t[keep]
    else:
        s = np.empty(0)
        t = np.empty(0)
        while s.size < points:               # rejection sampling of the surface's domain
            cs, ct = rng.uniform(0, 1, (2, 2 * points))
            keep = _in_domain(surface, cs, ct)
            s, t = np.concatenate([s, cs[keep]]), np.concatenate([t, ct[keep]])
        s, t = s[:points], t[:points]
    Sw = np.stack([_surface(surface, s, t, deformation_time(f, fps, period_frames), amplitude,
                            phase) for f in range(frames)])
    S = np.einsum('fij,fpj->fpi', poses[:, :3, :3], Sw) + poses[:, None, :3, 3]
    k = focal / (distance if projection == 'orthographic' else S[:, :, 2].mean(1))
    W = (np.broadcast_to(np.reshape(k, (-1, 1, 1)), (frames, 1, 1)) * S[:, :, :2])
    P = s.size
    return {'W': W.transpose(0, 2, 1).reshape(2 * frames, P), 'V': np.ones((frames, P)),
            'S': S, 'S_world': Sw}
