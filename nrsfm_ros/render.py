"""Renders a person can read: perspective 3-D views of published clouds, shaded by surface
normals or by depth, side by side with the ground truth and a heat map of each point's error
after the alignment the evaluation scores with (``core.metrics.frame_alignment``, metric B),
and a short video of the stream (GIF through Pillow, or MP4 through OpenCV).  NumPy, SciPy and
OpenCV (and Pillow for a GIF): no viewer, no matplotlib, and nothing in ``core`` imports it.

A view is a pinhole camera swung about the cloud's centre from the direction the recording
camera looked along (``YAW_DEG`` sideways, ``PITCH_DEG`` from above), so depth shows as shape;
points are splatted as discs whose radius follows the point spacing and the perspective, nearest
point first per pixel (a z-buffer by sorting).
"""
from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from .core.metrics import frame_alignment, match_ids, point_errors

SHADINGS = ('normals', 'depth')
VIDEO_FORMATS = ('gif', 'mp4', 'none')
PANEL_PX = 320                  # each panel is square
HEADER_PX = 22                  # title strip above each panel
YAW_DEG = 30.0                  # the view swings this far sideways ...
PITCH_DEG = 20.0                # ... and this far above the recording camera's line of sight
FOV_DEG = 35.0                  # full field of view of the render camera
NEIGHBOURS = 10                 # points of the local plane fit that gives a point's normal
MAX_SPLAT_PX = 4                # largest disc radius of a point (pixels)
SPLAT_SPACING = 0.9             # disc radius in units of the median point spacing
ERROR_PERCENTILE = 95.0         # heat-map colour scale: this percentile of the stream's errors
BACKGROUND = (240, 240, 240)    # BGR
GIF_SCALE = 0.75                # GIF frames are scaled down by this (file size)
NO_MATCH = (170, 170, 170)      # heat map: a point whose track id has no ground truth
TEXT = (40, 40, 40)
# normal shading, view frame (x right, y down, z forward): a grazing key light from the upper
# left shows folds, a fill light from the front keeps the rest readable
KEY_LIGHT = np.array([-0.7, -0.5, -0.5]) / np.linalg.norm([-0.7, -0.5, -0.5])
FILL_LIGHT = np.array([0.3, 0.0, -1.0]) / np.linalg.norm([0.3, 0.0, -1.0])
AMBIENT = 0.25
SURFACE_RGB = np.array([0.85, 0.82, 0.75])
DOWN = np.array([0.0, 1.0, 0.0])  # optical frames: y down


@dataclass(frozen=True)
class View:
    """A pinhole render camera: ``R`` (3, 3) rows are its x right, y down, z forward axes in the
    cloud's frame, ``eye`` (3,) its centre, ``f`` the focal length (px), ``size`` the square
    image side (px); ``near``, ``far`` the depth range the depth shading spans."""

    R: np.ndarray
    eye: np.ndarray
    f: float
    size: int
    near: float
    far: float

    def project(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixel coordinates uv (N, 2) and depth z (N,) of points X (N, 3)."""
        Xc = (np.asarray(X, dtype=np.float64) - self.eye) @ self.R.T
        z = Xc[:, 2]
        with np.errstate(divide='ignore', invalid='ignore'):
            uv = self.f * Xc[:, :2] / z[:, None] + self.size / 2.0
        return uv, z


def orbit_view(centre: np.ndarray, radius: float, size: int = PANEL_PX,
               yaw_deg: float = YAW_DEG, pitch_deg: float = PITCH_DEG,
               fov_deg: float = FOV_DEG) -> View:
    """The view of a sphere of ``radius`` about ``centre`` (the recording camera at the origin
    looks at it) from ``yaw_deg`` sideways and ``pitch_deg`` above that camera's line of
    sight, filling the image."""
    centre = np.asarray(centre, dtype=np.float64)
    if not (np.isfinite(centre).all() and np.isfinite(radius) and radius > 0):
        raise ValueError(f'view: centre {centre} and radius {radius} must be finite, radius > 0')
    n = np.linalg.norm(centre)
    z0 = centre / n if n > 1e-9 else np.array([0.0, 0.0, 1.0])
    x0 = np.cross(DOWN, z0)
    x0 = x0 / np.linalg.norm(x0) if np.linalg.norm(x0) > 1e-9 else np.array([1.0, 0.0, 0.0])
    y0 = np.cross(z0, x0)
    yaw, pitch = np.radians(yaw_deg), np.radians(pitch_deg)
    forward = np.array([-np.sin(yaw) * np.cos(pitch), np.sin(pitch), np.cos(yaw) * np.cos(pitch)])
    z = np.column_stack([x0, y0, z0]) @ forward
    x = np.cross(DOWN if abs(z @ DOWN) < 0.99 else y0, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    half = np.radians(fov_deg) / 2
    dist = 0.9 * radius / np.sin(half)
    return View(R=np.stack([x, y, z]), eye=centre - dist * z, f=size / 2 / np.tan(half),
                size=size, near=dist - radius, far=dist + radius)


def cloud_geometry(X: np.ndarray, k: int = NEIGHBOURS) -> tuple[np.ndarray, float]:
    """Unit normals (N, 3) of points X (N, 3) from the plane of their ``k`` nearest points (sign
    arbitrary) and the median nearest-neighbour spacing."""
    from scipy.spatial import cKDTree
    X = np.asarray(X, dtype=np.float64)
    if X.shape[0] < 3:
        return np.tile([0.0, 0.0, -1.0], (X.shape[0], 1)), 1.0
    k = min(k, X.shape[0])
    d, idx = cKDTree(X).query(X, k=k)
    spacing = float(np.median(d[:, 1]))
    Q = X[idx] - X[idx].mean(axis=1, keepdims=True)
    _, vecs = np.linalg.eigh(np.einsum('nki,nkj->nij', Q, Q))
    return vecs[:, :, 0], spacing


def _disc_offsets(r: int) -> tuple[np.ndarray, np.ndarray]:
    o = np.arange(-r, r + 1)
    ox, oy = (a.ravel() for a in np.meshgrid(o, o))
    return np.stack([ox, oy], axis=1), np.hypot(ox, oy)


_OFFSETS, _OFFSET_NORMS = _disc_offsets(MAX_SPLAT_PX)


def splat(view: View, X: np.ndarray, colours: np.ndarray, spacing: float,
          image: np.ndarray | None = None) -> np.ndarray:
    """Paint points X (N, 3) with ``colours`` (N, 3) uint8 BGR as discs (radius
    ``SPLAT_SPACING`` x ``spacing`` in perspective, 0.5..``MAX_SPLAT_PX`` px), the nearest
    point winning each pixel, onto ``image`` (size x size x 3; default a blank one)."""
    size = view.size
    img = np.empty((size, size, 3), np.uint8) if image is None else image
    if image is None:
        img[:] = BACKGROUND
    uv, z = view.project(X)
    ok = (z > 1e-9) & np.isfinite(uv).all(axis=1)
    if not ok.any():
        return img
    uv, z, colours = uv[ok], z[ok], np.asarray(colours, np.uint8)[ok]
    r = np.clip(SPLAT_SPACING * spacing * view.f / z, 0.5, MAX_SPLAT_PX)
    pt, k = np.nonzero(_OFFSET_NORMS[None, :] <= r[:, None])
    px = np.rint(uv[pt, 0]).astype(np.int64) + _OFFSETS[k, 0]
    py = np.rint(uv[pt, 1]).astype(np.int64) + _OFFSETS[k, 1]
    inside = (px >= 0) & (px < size) & (py >= 0) & (py < size)
    pt, lin = pt[inside], (py * size + px)[inside]
    order = np.lexsort((z[pt], lin))          # by pixel, then nearest first
    first = np.unique(lin[order], return_index=True)[1]
    win = order[first]
    img.reshape(-1, 3)[lin[win]] = colours[pt[win]]
    return img


def shade(view: View, X: np.ndarray, normals: np.ndarray, shading: str) -> np.ndarray:
    """BGR colours (N, 3) uint8 of points X seen from ``view``: ``normals``: Lambert shading of
    the view-frame normals (``KEY_LIGHT``, ``FILL_LIGHT``) on a surface tinted by the normal's
    direction; ``depth``: near red .. far blue over the view's depth range."""
    if shading not in SHADINGS:
        raise ValueError(f'shading={shading!r}: expected one of {list(SHADINGS)}')
    X = np.asarray(X, dtype=np.float64)
    if shading == 'depth':
        z = (X - view.eye) @ view.R[2]
        t = np.clip((view.far - z) / max(view.far - view.near, 1e-12), 0, 1)
        return cv2.applyColorMap(np.rint(255 * t).astype(np.uint8)[:, None],
                                 cv2.COLORMAP_TURBO)[:, 0]
    n = np.asarray(normals, dtype=np.float64) @ view.R.T
    n *= np.where(n[:, 2] > 0, -1.0, 1.0)[:, None]          # facing the viewer
    key = np.clip(n @ KEY_LIGHT, 0, 1)
    fill = np.clip(n @ FILL_LIGHT, 0, 1)
    lit = AMBIENT + (1 - AMBIENT) * (0.8 * key + 0.2 * fill)
    tint = 0.5 + 0.5 * n * np.array([1.0, -1.0, -1.0])      # normal-map hue, x red, up green
    rgb = lit[:, None] * (0.6 * SURFACE_RGB + 0.4 * tint)
    return np.clip(255 * rgb[:, ::-1], 0, 255).astype(np.uint8)


def heat(err: np.ndarray, vmax: float) -> np.ndarray:
    """BGR colours (N, 3) uint8 of errors on the inferno scale, 0 .. ``vmax`` (saturating)."""
    t = np.clip(np.asarray(err, dtype=np.float64) / max(vmax, 1e-12), 0, 1)
    return cv2.applyColorMap(np.rint(255 * t).astype(np.uint8)[:, None],
                             cv2.COLORMAP_INFERNO)[:, 0]


def _panel(title: str, body: np.ndarray) -> np.ndarray:
    head = np.empty((HEADER_PX, body.shape[1], 3), np.uint8)
    head[:] = BACKGROUND
    cv2.putText(head, title, (6, HEADER_PX - 7), cv2.FONT_HERSHEY_SIMPLEX, 0.45, TEXT, 1,
                cv2.LINE_AA)
    return np.vstack([head, body])


def _colour_bar(img: np.ndarray, vmax: float) -> None:
    size = img.shape[1]
    x0, x1, y0, y1 = 40, size - 40, size - 24, size - 14
    ramp = heat(np.linspace(0, vmax, x1 - x0), vmax)
    img[y0:y1, x0:x1] = ramp[None, :, :]
    for x, label in ((x0, '0'), (x1, f'{vmax:.3g}')):
        cv2.putText(img, label, (x - 4 * len(label), y1 + 11), cv2.FONT_HERSHEY_SIMPLEX, 0.35,
                    TEXT, 1, cv2.LINE_AA)
    cv2.putText(img, 'error / RMS radius', (x0, y0 - 4), cv2.FONT_HERSHEY_SIMPLEX, 0.35, TEXT,
                1, cv2.LINE_AA)


def _blank(view: View, text: str) -> np.ndarray:
    img = np.empty((view.size, view.size, 3), np.uint8)
    img[:] = BACKGROUND
    cv2.putText(img, text, (12, view.size // 2), cv2.FONT_HERSHEY_SIMPLEX, 0.45, TEXT, 1,
                cv2.LINE_AA)
    return img


@dataclass(frozen=True)
class FrameErrors:
    """One cloud against its ground-truth frame: ``aligned`` (n, 3) every finite point mapped
    into the ground truth's frame by the metric-B alignment of the matched points, ``error``
    (n,) each point's error (``core.metrics.point_errors``; NaN where its id has no ground
    truth), ``e3d`` the frame's metric B (the RMS of the matched errors), ``matched`` the
    number of matched points; ``aligned`` is None when fewer than ``min_points`` matched."""

    aligned: np.ndarray | None
    error: np.ndarray
    e3d: float
    matched: int


def frame_errors(X: np.ndarray, ids: np.ndarray, X_gt: np.ndarray, gt_ids: np.ndarray,
                 min_points: int = 10) -> FrameErrors:
    """Match a cloud X (n, 3) with track ids (n,) to ground truth X_gt (P, 3) with ``gt_ids``
    (P,) by id and align it as the evaluation does (non-finite points dropped)."""
    X = np.asarray(X, dtype=np.float64)
    finite = np.isfinite(X).all(axis=1)
    X, ids = X[finite], np.asarray(ids)[finite]
    ok, cols = match_ids(ids, gt_ids)
    err = np.full(X.shape[0], np.nan)
    if cols.size < max(min_points, 3):
        return FrameErrors(None, err, float('nan'), int(cols.size))
    gt = np.asarray(X_gt, dtype=np.float64)[cols]
    err[ok] = point_errors(X[ok], gt)
    aligned = frame_alignment(X[ok], gt).apply(X)
    return FrameErrors(aligned, err, float(np.sqrt(np.mean(err[ok] ** 2))), int(cols.size))


def compare_image(fe: FrameErrors | None, X_gt: np.ndarray, view: View, shading: str,
                  vmax: float, label: str = '') -> np.ndarray:
    """Three panels side by side, one view: the aligned reconstruction and the ground truth
    X_gt (P, 3) shaded alike, and the error heat map of the reconstruction's points (grey:
    no ground truth for the id) with its colour bar.  ``fe`` None: no cloud for the frame."""
    X_gt = np.asarray(X_gt, dtype=np.float64)
    n_gt, sp_gt = cloud_geometry(X_gt)
    gt = splat(view, X_gt, shade(view, X_gt, n_gt, shading), sp_gt)
    if fe is None or fe.aligned is None:
        why = 'no cloud for this frame' if fe is None else \
            f'unscored: {fe.matched} point(s) matched'
        rec, hot = _blank(view, why), _blank(view, why)
        e_text = ''
    else:
        n, sp = cloud_geometry(fe.aligned)
        rec = splat(view, fe.aligned, shade(view, fe.aligned, n, shading), sp)
        colours = np.where(np.isfinite(fe.error)[:, None], heat(np.nan_to_num(fe.error), vmax),
                           np.array(NO_MATCH, np.uint8)[None, :])
        hot = splat(view, fe.aligned, colours, sp)
        e_text = f'  e3D {fe.e3d:.4f}'
    _colour_bar(hot, vmax)
    prefix = f'{label}  ' if label else ''
    return np.hstack([_panel(f'{prefix}reconstruction ({shading})', rec),
                      _panel('ground truth', gt), _panel(f'error{e_text}', hot)])


@dataclass
class RenderResult:
    """What ``render_stream`` wrote: ``stills`` PNG paths, ``video`` (None: none), ``frames``
    rendered into the video, ``vmax`` the heat map's top, ``seconds_per_frame`` render time."""

    stills: list[Path] = field(default_factory=list)
    video: Path | None = None
    frames: int = 0
    vmax: float = float('nan')
    seconds_per_frame: float = 0.0


def stream_view(S_gt: np.ndarray, size: int = PANEL_PX) -> tuple[np.ndarray, float]:
    """(centres (F, 3), radius) for one view per frame that keeps the scale steady: each
    frame's ground-truth centroid and the largest distance of a point from it."""
    S = np.asarray(S_gt, dtype=np.float64)
    centres = np.nanmean(S, axis=1)
    radius = float(np.nanmax(np.linalg.norm(S - centres[:, None], axis=2)))
    return centres, radius


def render_stream(clouds: dict[int, tuple[np.ndarray, np.ndarray]], S_gt: np.ndarray,
                  gt_ids: np.ndarray, out_dir: str | Path, shading: str = 'normals',
                  video: str = 'gif', fps: float = 10.0, stills: Sequence[int] | None = None,
                  min_points: int = 10, vmax: float | None = None,
                  size: int = PANEL_PX) -> RenderResult:
    """Render a stream of clouds ``{frame: (X (n, 3), track_id (n,))}`` against ground truth
    S_gt (F, P, 3) with columns ``gt_ids`` (P,): ``compare_FFF.png`` for the ``stills`` frames
    (default the first, middle and last frame with a cloud) and ``stream.gif`` or
    ``stream.mp4`` of every ground-truth frame at ``fps`` (``video='none'``: no video).  The
    heat map's scale is fixed for the stream (``vmax``; default the ``ERROR_PERCENTILE``-th
    percentile of every matched point's error)."""
    if shading not in SHADINGS:
        raise ValueError(f'shading={shading!r}: expected one of {list(SHADINGS)}')
    if video not in VIDEO_FORMATS:
        raise ValueError(f'video={video!r}: expected one of {list(VIDEO_FORMATS)}')
    if not (np.isfinite(fps) and fps > 0):
        raise ValueError(f'fps={fps!r}: expected a number > 0')
    S_gt = np.asarray(S_gt, dtype=np.float64)
    F = S_gt.shape[0]
    frames = sorted(f for f in clouds if 0 <= f < F)
    if not frames:
        raise ValueError('render: no cloud has a ground-truth frame')
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    errs = {f: frame_errors(*clouds[f], S_gt[f], gt_ids, min_points) for f in frames}
    if vmax is None:
        pooled = np.concatenate([e.error[np.isfinite(e.error)] for e in errs.values()] or
                                [np.zeros(0)])
        vmax = float(np.percentile(pooled, ERROR_PERCENTILE)) if pooled.size else 1.0
    if not (np.isfinite(vmax) and vmax > 0):
        vmax = 1.0
    centres, radius = stream_view(S_gt, size)
    if stills is None:
        stills = sorted({frames[0], frames[len(frames) // 2], frames[-1]})
    bad = [f for f in stills if not 0 <= f < F]
    if bad:
        raise ValueError(f'stills: frame(s) {bad} outside the ground truth 0..{F - 1}')
    result = RenderResult(vmax=vmax)
    todo = range(F) if video != 'none' else sorted(set(stills))
    images = []
    for f in todo:
        img = compare_image(errs.get(f), S_gt[f], orbit_view(centres[f], radius, size),
                            shading, vmax, label=f'frame {f}')
        if f in stills:
            path = out / f'compare_{f:03d}.png'
            cv2.imwrite(str(path), img)
            result.stills.append(path)
        if video != 'none':
            images.append(img)
    result.frames = len(images)
    result.seconds_per_frame = (time.perf_counter() - t0) / max(len(todo), 1)
    if images:
        result.video = write_video(out / f'stream.{video}', images, fps)
    return result


def write_video(path: str | Path, images: Sequence[np.ndarray], fps: float) -> Path:
    """An animated GIF (Pillow, frames scaled by ``GIF_SCALE``, 255 colours each, no dither) or
    an MP4 (OpenCV's encoder), by the suffix, of BGR frames of one size."""
    path = Path(path)
    if not images:
        raise ValueError(f'{path}: no frames')
    if path.suffix == '.gif':
        try:
            from PIL import Image
        except ImportError as err:
            raise RuntimeError(f'{path}: a GIF needs Pillow (.venv/bin/pip install -r '
                               'requirements.txt), or write an MP4') from err
        frames = [Image.fromarray(np.ascontiguousarray(cv2.resize(
            img, None, fx=GIF_SCALE, fy=GIF_SCALE, interpolation=cv2.INTER_AREA)[:, :, ::-1]))
            .quantize(colors=255, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE)
            for img in images]
        frames[0].save(path, format='GIF', save_all=True, append_images=frames[1:],
                       duration=int(round(1000 / fps)), loop=0)
    elif path.suffix == '.mp4':
        h, w = images[0].shape[:2]
        writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*'mp4v'), fps,
                                 (w - w % 2, h - h % 2))
        if not writer.isOpened():
            raise RuntimeError(f'{path}: this OpenCV build has no MP4 encoder (use gif)')
        for img in images:
            writer.write(np.ascontiguousarray(img[:h - h % 2, :w - w % 2]))
        writer.release()
    else:
        raise ValueError(f'{path}: expected a .gif or .mp4 name')
    return path


def render_cloud(path: str | Path, X: np.ndarray, rgb: np.ndarray | None = None,
                 shading: str = 'depth', size: int = 480) -> None:
    """PNG of one cloud X (N, 3) alone (no ground truth), in the oblique perspective view of
    its own centre and extent: coloured by ``rgb`` (N, 3) uint8 where given (the cloud's own
    colours), else shaded by ``shading``; non-finite points are left out."""
    X = np.asarray(X, dtype=np.float64)
    finite = np.isfinite(X).all(axis=1)
    if rgb is not None and np.shape(rgb) != (X.shape[0], 3):
        raise ValueError(f'rgb: expected shape ({X.shape[0]}, 3), got {np.shape(rgb)}')
    X = X[finite]
    if X.shape[0] == 0:
        cv2.imwrite(str(path), _blank(orbit_view(np.array([0, 0, 1.0]), 1.0, size), 'no points'))
        return
    c = X.mean(axis=0)
    r = float(np.max(np.linalg.norm(X - c, axis=1))) or 1.0
    view = orbit_view(c, r, size)
    n, sp = cloud_geometry(X)
    colours = shade(view, X, n, shading) if rgb is None else \
        np.asarray(rgb, np.uint8)[finite][:, ::-1]
    cv2.imwrite(str(path), splat(view, X, colours, sp))
