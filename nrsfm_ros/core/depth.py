"""Depth image of a reconstructed track set (the reconstructor's ``nrsfm/depth``)."""
from __future__ import annotations

import cv2
import numpy as np


def depth_image(uv: np.ndarray, z: np.ndarray, size: tuple[int, int],
                spacing: float | None = None) -> np.ndarray:
    """Depth (H, W) float32, NaN off the surface, from tracks at image positions ``uv`` (P, 2)
    with depths ``z`` (P,).

    Each track is splatted to its nearest pixel (the nearest depth wins where tracks share a
    pixel); the surface is the closing of the splats by a disc of the track ``spacing`` (px;
    default from the track density), and each of its pixels gets the normalised-convolution
    average of the splatted depths within that disc.  O(H W) with OpenCV, a few ms at 320x240.
    """
    h, w = size
    uv = np.asarray(uv, np.float64)
    z = np.asarray(z, np.float64)
    if uv.shape != (z.size, 2):
        raise ValueError(f'uv: expected shape ({z.size}, 2), got {uv.shape}')
    out = np.full((h, w), np.nan, np.float32)
    finite = np.isfinite(uv).all(axis=1) & np.isfinite(z)
    xi, yi = np.rint(np.where(finite[:, None], uv, -1.0)).astype(np.int64).T
    ok = finite & (xi >= 0) & (xi < w) & (yi >= 0) & (yi < h)
    if ok.sum() < 3:
        return out
    xi, yi, zk = xi[ok], yi[ok], z[ok]
    if spacing is None:          # per column: NumPy's axis-0 reduction of (P, 2) is ~40x slower
        u, v = uv[ok, 0], uv[ok, 1]
        span = np.array([u.max() - u.min(), v.max() - v.min()]) + 1.0
        spacing = float(np.sqrt(span[0] * span[1] / ok.sum()))
    r = int(np.clip(np.ceil(spacing), 1, max(h, w)))
    # everything on the tracks' bounding box grown by 2r + 1 (the image clipped), the same
    # output: a pixel nearer the box's edge than r lies over r + 1 from every track, so its
    # closing is 0 there whatever the erosion saw beyond the box (about half a 640x480 frame)
    m = 2 * r + 1
    x0, x1 = max(int(xi.min()) - m, 0), min(int(xi.max()) + m + 1, w)
    y0, y1 = max(int(yi.min()) - m, 0), min(int(yi.max()) + m + 1, h)
    bw = x1 - x0
    # float32 splats: rounding is monotonic, so the nearest depth is the same as in float64
    splat = np.full((y1 - y0) * bw, np.inf, np.float32)
    np.minimum.at(splat, (yi - y0) * bw + (xi - x0), zk.astype(np.float32))
    splat = splat.reshape(y1 - y0, bw)
    hit = splat < np.inf
    mask = hit.view(np.uint8)
    splat[~hit] = 0.0
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    surface = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, kernel).view(bool)
    k = kernel.astype(np.float32)
    num = cv2.filter2D(splat, -1, k, borderType=cv2.BORDER_CONSTANT)
    den = cv2.filter2D(mask, cv2.CV_32F, k, borderType=cv2.BORDER_CONSTANT)
    fill = surface & (den > 0)
    out[y0:y1, x0:x1][fill] = num[fill] / den[fill]
    return out
