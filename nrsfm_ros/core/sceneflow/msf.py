"""MSF: RGB-D multi-frame scene flow with piecewise rigid motion (METHODS §11.2).

The reference frame is over-segmented (:func:`slic`: intensity, image position and depth); every
segment s gets one rigid motion ``T_s`` (camera-ref -> camera-c coordinates) per frame c, found
by damped Gauss-Newton on

    sum_p w_I rho(I_c(pi(T_s X_p)) - I_ref(p)) / sigma_I
  + sum_p w_D rho(n_c . (T_s X_p - V_c(pi(T_s X_p)))) / sigma_D   (projective point-to-plane ICP)
  + nu sum_(s,s') w_ss' |T_s P - T_s' P|^2 / sigma_D                 (neighbour rigidity, at points
                                                                      P shared by the two segments)

(rho: Huber by IRLS weights), coarse to fine over an image pyramid, with se(3) increments and a
sparse 6S x 6S normal-equation solve.  Frames are processed from the reference to every later
frame, each warm-started from the previous one; when too little of the reference stays
consistent a new reference is selected and the flow is chained through it.  A per-pixel
refinement then moves each pixel off its segment's motion (``MSF._refine``), its windows and
high-pass images within the pixel's depth layer (:func:`depth_layers`: a surface is not mixed
with what lies behind its silhouette).  The output is the camera-frame flow ``X_c - X_ref`` of
every reference pixel with depth (see :mod:`.definition`), NaN elsewhere.

Baselines of the benchmark: :func:`dis_depth_flow` (DIS optical flow + depth back-projection)
and per-segment ICP (``MSFConfig(photometric_weight=0, smoothness=0)``).
Pure NumPy/SciPy/OpenCV: no ROS, no files.
"""
from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import cv2
import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components


# ------------------------------------------------------------------ input helpers

def depth_metres(depth: np.ndarray) -> np.ndarray:
    """A depth image as float32 metres with NaN where unknown: float input is metres (NaN,
    inf, 0 or negative: unknown), integer input (16UC1) is millimetres (0: unknown)."""
    d = np.asarray(depth)
    if d.ndim != 2:
        raise ValueError(f'depth: expected an H x W image, got shape {d.shape}')
    if np.issubdtype(d.dtype, np.integer):
        out = d.astype(np.float32) * np.float32(1e-3)
    elif np.issubdtype(d.dtype, np.floating):
        out = d.astype(np.float32, copy=True)
    else:
        raise ValueError(f'depth: dtype {d.dtype} is neither metres (float) nor millimetres (int)')
    out[~(np.isfinite(out) & (out > 0))] = np.nan
    return out


def to_gray(image: np.ndarray) -> np.ndarray:
    """uint8/float rgb or gray image -> float32 gray (0..255)."""
    a = np.asarray(image)
    if a.ndim == 3 and a.shape[2] in (3, 4):
        a = cv2.cvtColor(a[..., :3].astype(np.float32), cv2.COLOR_RGB2GRAY)
    elif a.ndim != 2:
        raise ValueError(f'image: expected H x W or H x W x 3, got shape {a.shape}')
    return a.astype(np.float32)


def back_project(depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """(H, W, 3) camera-frame points of a depth image (NaN where the depth is)."""
    H, W = depth.shape
    u, v = np.meshgrid(np.arange(W, dtype=np.float32), np.arange(H, dtype=np.float32))
    z = depth.astype(np.float32)
    return np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], axis=-1)


def highpass(gray: np.ndarray, valid: np.ndarray, sigma: float) -> np.ndarray:
    """gray minus its Gaussian-weighted local mean over the ``valid`` pixels (normalised
    convolution, so that the background does not leak in), 0 outside ``valid``: a structure
    image that slow shading changes leave alone.  ``sigma`` 0: gray unchanged."""
    if sigma <= 0:
        return np.asarray(gray, np.float32)
    m = np.asarray(valid, np.float32)
    g = np.where(valid, gray, 0).astype(np.float32)
    mean = cv2.GaussianBlur(g, (0, 0), sigma) / np.maximum(cv2.GaussianBlur(m, (0, 0), sigma),
                                                           1e-3)
    return np.where(valid, g - mean, 0).astype(np.float32)


def depth_noise(depth: np.ndarray) -> float:
    """Robust estimate (m) of a depth image's noise sigma: the median absolute deviation of
    each pixel from the mean of its 4 neighbours (where all five have depth), which on a
    smooth surface is noise times sqrt(1.25); for quantised depth (a structured-light
    sensor's disparity steps, or millimetres: over a fifth of the neighbours equal, where the
    MAD sees no noise at all) at least the quantisation error, step / sqrt(12), the step the
    median of the neighbours' non-zero differences.  0.0 when no pixel qualifies."""
    z = np.asarray(depth, np.float32)
    ok = np.isfinite(z)
    zf = np.where(ok, z, 0).astype(np.float32)
    k = np.array([[0, .25, 0], [.25, 0, .25], [0, .25, 0]], np.float32)
    res = (zf - cv2.filter2D(zf, -1, k, borderType=cv2.BORDER_CONSTANT))[
        cv2.erode(ok.astype(np.uint8), np.ones((3, 3), np.uint8), borderType=cv2.BORDER_CONSTANT,
                  borderValue=0) > 0]
    if res.size == 0:
        return 0.0
    mad = float(1.4826 * np.median(np.abs(res - np.median(res))) / np.sqrt(1.25))
    d = np.concatenate([(z[:, 1:] - z[:, :-1]).ravel(), (z[1:] - z[:-1]).ravel()])
    zz = np.concatenate([z[:, 1:].ravel(), z[1:].ravel()])
    with np.errstate(invalid='ignore'):
        d = np.abs(d[np.isfinite(d) & (np.abs(d) < QUANT_SMOOTH * zz)])
    if d.size == 0 or np.mean(d == 0) <= QUANT_EQUAL:
        return mad
    step = float(np.median(d[d > 0])) if (d > 0).any() else 0.0
    return max(mad, step / np.sqrt(12.0))


RAY_CLAMP = 2.0     # _refine: along-ray moves from a segment's rigid motion beyond this x
#   max_depth_residual are reset (the face 4 m before a wall: 1.38 -> 0.53 mm; 1x: 0.44 mm but
#   the flag's wall cases 2-9% worse, 2x: none worse)
QUANT_EQUAL = 0.2    # depth_noise: quantised where more of the neighbour pairs are equal
QUANT_SMOOTH = 0.05  # depth_noise: neighbour pairs nearer than this x depth (not an edge)


def depth_edges(depth: np.ndarray, min_jump: float, rel_jump: float = 0.03) -> np.ndarray:
    """(H, W) bool: pixels with depth beside a 4-neighbour more than ``max(min_jump, rel_jump
    z)`` metres nearer or further (a silhouette before a background, a self-occlusion)."""
    z = np.asarray(depth, np.float32)
    thr = np.maximum(np.float32(min_jump), np.float32(rel_jump) * np.nan_to_num(z))
    edge = np.zeros(z.shape, bool)
    for a, b in (((slice(None), slice(1, None)), (slice(None), slice(None, -1))),
                 ((slice(1, None), slice(None)), (slice(None, -1), slice(None)))):
        with np.errstate(invalid='ignore'):
            jump = np.abs(z[a] - z[b]) > np.maximum(thr[a], thr[b])
        edge[a] |= jump
        edge[b] |= jump
    return edge


def depth_layers(depth: np.ndarray, min_jump: float, max_layers: int = 4) -> np.ndarray:
    """(H, W) int32 layer of each pixel with depth (-1 without): the regions that depth edges
    (:func:`depth_edges`) separate (holes of up to ~6 px, a sensor's dropouts, do not), edge
    pixels joined to the nearest-depth neighbouring region; the ``max_layers`` - 1 largest
    regions keep their own layer, the rest share one.  A window that sums over one layer
    does not mix a surface with what is behind it."""
    z = np.asarray(depth, np.float32)
    known = np.isfinite(z)
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (7, 7))
    closed = cv2.morphologyEx(known.astype(np.uint8), cv2.MORPH_CLOSE, disc) > 0
    # the small holes filled with the furthest depth around them, so that a hole band along a
    # silhouette (a structured-light sensor's shadow) still shows the jump across it
    far = cv2.dilate(np.where(known, z, 0).astype(np.float32), disc)
    edge = depth_edges(np.where(known, z, np.where(closed, far, np.nan)), min_jump)
    n, lab = cv2.connectedComponents((closed & ~edge).astype(np.uint8), connectivity=4)
    lab = np.where(known, lab.astype(np.int32) - 1, -1)  # -1: no depth, or an edge pixel
    todo = known & (lab < 0)
    H, W = z.shape
    for _ in range(3):                                   # edge pixels: nearest-depth neighbour
        if not todo.any():
            break
        best = np.full(z.shape, np.inf, np.float32)
        pick = np.full(z.shape, -1, np.int32)
        zp = np.pad(np.where(known, z, np.nan), 1, constant_values=np.nan)
        lp = np.pad(lab, 1, constant_values=-1)
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                if dy == dx == 0:
                    continue
                zn = zp[1 + dy:1 + dy + H, 1 + dx:1 + dx + W]
                ln = lp[1 + dy:1 + dy + H, 1 + dx:1 + dx + W]
                with np.errstate(invalid='ignore'):
                    d = np.where(ln >= 0, np.abs(zn - z), np.inf)
                better = todo & (d < best)
                best[better], pick[better] = d[better], ln[better]
        lab = np.where(todo & (pick >= 0), pick, lab)
        todo = known & (lab < 0)
    lab[todo] = n - 1                                    # edge pixels left: a region of theirs
    sizes = np.bincount(lab[lab >= 0], minlength=n)
    order = np.argsort(-sizes, kind='stable')
    rank = np.empty(n, np.int32)
    rank[order] = np.minimum(np.arange(n), max_layers - 1)
    return np.where(lab >= 0, rank[np.maximum(lab, 0)], -1).astype(np.int32)


def layered_highpass(gray: np.ndarray, layers: np.ndarray, sigma: float) -> np.ndarray:
    """:func:`highpass` within each depth layer (``layers``, :func:`depth_layers`; -1: no
    depth), so that a surface's structure image does not take in what is behind it."""
    n = int(layers.max()) + 1 if layers.size else 0
    if n <= 1 or sigma <= 0:
        return highpass(gray, layers >= 0, sigma)
    out = np.zeros(layers.shape, np.float32)
    for k in range(n):
        m = layers == k
        out[m] = highpass(gray, m, sigma)[m]
    return out


def _check_K(K: np.ndarray) -> np.ndarray:
    K = np.asarray(K, np.float64)
    if K.shape != (3, 3) or not (K[0, 0] > 0 and K[1, 1] > 0):
        raise ValueError(f'K: expected a 3x3 intrinsic matrix with fx, fy > 0, got {K.tolist()}')
    return K


# ------------------------------------------------------------------ SLIC over-segmentation

def slic(gray: np.ndarray, depth: np.ndarray, n_segments: int = 300, compactness: float = 10.0,
         depth_scale: float = 0.02, iterations: int = 5) -> np.ndarray:
    """Vectorised SLIC of the pixels with depth: k-means on (intensity, x, y, depth) with every
    pixel compared to the 3x3 grid cells around it.  ``compactness``: intensity units per grid
    step; ``depth_scale``: metres worth one grid step.  Returns labels (H, W) int32, 0..S-1,
    -1 where there is no depth; every segment is 4-connected."""
    if n_segments < 1:
        raise ValueError(f'n_segments={n_segments}: expected >= 1')
    g = np.asarray(gray, np.float32)
    z = np.asarray(depth, np.float32)
    if g.shape != z.shape:
        raise ValueError(f'gray: shape {g.shape} differs from depth {z.shape}')
    H, W = g.shape
    ok = np.isfinite(z)
    labels = np.full((H, W), -1, np.int32)
    n_ok = int(ok.sum())
    if n_ok == 0:
        return labels
    step = max(2.0, np.sqrt(n_ok / n_segments))
    ys, xs = np.nonzero(ok)
    feat = np.stack([g[ys, xs], xs.astype(np.float32), ys.astype(np.float32), z[ys, xs]], 1)
    gh, gw = int(np.ceil(H / step)), int(np.ceil(W / step))
    cy = np.minimum((ys / step).astype(int), gh - 1)
    cx = np.minimum((xs / step).astype(int), gw - 1)
    cell = cy * gw + cx
    n_cells = gh * gw
    # seeds: the mean of each cell's pixels
    cnt = np.bincount(cell, minlength=n_cells).astype(np.float64)
    centres = np.stack([np.bincount(cell, feat[:, k], n_cells) for k in range(4)], 1) \
        / np.maximum(cnt, 1)[:, None]
    alive = cnt > 0
    wI = 1.0 / compactness ** 2
    wxy = 1.0 / step ** 2
    wz = 1.0 / depth_scale ** 2
    offs = [(dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1)]
    assign = cell
    for _ in range(iterations):
        best = np.full(n_ok, np.inf, np.float32)
        for dy, dx in offs:
            ny, nx = cy + dy, cx + dx
            inside = (ny >= 0) & (ny < gh) & (nx >= 0) & (nx < gw)
            c = np.where(inside, ny * gw + nx, 0)
            ce = centres[c]
            d = (wI * (feat[:, 0] - ce[:, 0]) ** 2
                 + wxy * ((feat[:, 1] - ce[:, 1]) ** 2 + (feat[:, 2] - ce[:, 2]) ** 2)
                 + wz * (feat[:, 3] - ce[:, 3]) ** 2)
            d = np.where(inside & alive[c], d, np.inf).astype(np.float32)
            better = d < best
            best = np.where(better, d, best)
            assign = np.where(better, c, assign)
        cnt = np.bincount(assign, minlength=n_cells).astype(np.float64)
        alive = cnt > 0
        new = np.stack([np.bincount(assign, feat[:, k], n_cells) for k in range(4)], 1) \
            / np.maximum(cnt, 1)[:, None]
        centres = np.where(alive[:, None], new, centres)
    labels[ys, xs] = assign
    return _connected(labels, min_size=max(4, int(step * step / 4)))


def _connected(labels: np.ndarray, min_size: int) -> np.ndarray:
    """Split every label into its 4-connected pieces, merge pieces under ``min_size`` pixels
    into the nearest kept piece, relabel 0..S-1 (-1 stays -1)."""
    H, W = labels.shape
    idx = np.arange(H * W).reshape(H, W)
    lab = labels
    e = []
    for a, b in ((lab[:, :-1], lab[:, 1:]), (lab[:-1, :], lab[1:, :])):
        same = (a == b) & (a >= 0)
        e.append(same)
    r = np.concatenate([idx[:, :-1][e[0]], idx[:-1, :][e[1]]])
    c = np.concatenate([idx[:, 1:][e[0]], idx[1:, :][e[1]]])
    graph = sp.coo_matrix((np.ones(r.size, np.int8), (r, c)), shape=(H * W, H * W))
    _, comp = connected_components(graph, directed=False)
    comp = comp.reshape(H, W)
    valid = lab >= 0
    sizes = np.bincount(comp[valid], minlength=H * W)
    keep = valid & (sizes[comp] >= min_size)
    if not keep.any():
        keep = valid
    if (valid & ~keep).any():
        from scipy.ndimage import distance_transform_edt
        _, (iy, ix) = distance_transform_edt(~keep, return_indices=True)
        comp = np.where(keep, comp, comp[iy, ix])
    out = np.full((H, W), -1, np.int32)
    _, dense = np.unique(comp[valid], return_inverse=True)
    out[valid] = dense.astype(np.int32)
    return out


def segment_graph(labels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Neighbouring segment pairs (E, 2) (a < b) and their shared boundary length (E,)."""
    pairs = []
    for a, b in ((labels[:, :-1], labels[:, 1:]), (labels[:-1, :], labels[1:, :])):
        m = (a != b) & (a >= 0) & (b >= 0)
        pairs.append(np.stack([np.minimum(a[m], b[m]), np.maximum(a[m], b[m])], 1))
    p = np.concatenate(pairs)
    if p.size == 0:
        return np.empty((0, 2), np.int64), np.empty(0)
    uniq, counts = np.unique(p, axis=0, return_counts=True)
    return uniq.astype(np.int64), counts.astype(np.float64)


# ------------------------------------------------------------------ SE(3) helpers

def _exp_so3(w: np.ndarray) -> np.ndarray:
    """Rodrigues, vectorised: (S, 3) rotation vectors -> (S, 3, 3)."""
    th = np.linalg.norm(w, axis=1)
    k = w / np.maximum(th, 1e-12)[:, None]
    Kx = np.zeros((w.shape[0], 3, 3))
    Kx[:, 0, 1], Kx[:, 0, 2], Kx[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    Kx[:, 1, 0], Kx[:, 2, 0], Kx[:, 2, 1] = k[:, 2], -k[:, 1], k[:, 0]
    s, c = np.sin(th)[:, None, None], np.cos(th)[:, None, None]
    return np.eye(3) + s * Kx + (1 - c) * (Kx @ Kx)


def _bilinear(img: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear samples (N, C) float32 of img (H, W, C) float32 at (u, v), clamped to the image
    (the border replicated).  Exact weights: cv2.remap's own bilinear mode quantises them to
    1/32 px, 0.1-0.6 mm of a point at 4 m, more than the sub-millimetre flow this is for; so
    remap only gathers the four neighbours (nearest, integer maps) and the weights are applied
    here.  The points go in rows of 4096 (remap's sides are limited to 32767)."""
    H, W, C = img.shape
    u = np.clip(u, 0, W - 1)
    v = np.clip(v, 0, H - 1)
    x0 = np.minimum(u.astype(np.int32), max(W - 2, 0))
    y0 = np.minimum(v.astype(np.int32), max(H - 2, 0))
    a = (u - x0).astype(np.float32)[:, None]
    b = (v - y0).astype(np.float32)[:, None]
    n, row = u.size, 4096
    pad = (-n) % row
    mx = np.concatenate([x0, np.zeros(pad, np.int32)]).reshape(-1, row)
    my = np.concatenate([y0, np.zeros(pad, np.int32)]).reshape(-1, row)

    def at(dx: int, dy: int) -> np.ndarray:
        m = np.dstack([mx + dx, my + dy]).astype(np.int16)
        return cv2.remap(img, m, None, cv2.INTER_NEAREST).reshape(-1, C)[:n]
    dx, dy = int(W > 1), int(H > 1)
    top = at(0, 0)
    top += (at(dx, 0) - top) * a
    bottom = at(0, dy)
    bottom += (at(dx, dy) - bottom) * a
    top += (bottom - top) * b
    return top


def _block_pcg(Hm: sp.csr_matrix, b: np.ndarray, blocks: np.ndarray, iterations: int = 40,
               tol: float = 1e-8) -> np.ndarray:
    """Solve Hm x = b (symmetric positive definite) by conjugate gradients preconditioned
    with the inverses of the 6x6 diagonal blocks (a Gauss-Newton step needs no exact solve)."""
    Minv = np.linalg.inv(blocks)
    S = blocks.shape[0]

    def prec(r: np.ndarray) -> np.ndarray:
        return np.einsum('sij,sj->si', Minv, r.reshape(S, 6)).ravel()
    x = np.zeros_like(b)
    r = b.copy()
    z = prec(r)
    p = z.copy()
    rz = r @ z
    stop = tol * max(np.sqrt(b @ b), 1e-300)
    for _ in range(iterations):
        Ap = Hm @ p
        alpha = rz / max(p @ Ap, 1e-300)
        x += alpha * p
        r -= alpha * Ap
        if np.sqrt(r @ r) < stop:
            break
        z = prec(r)
        rz_new = r @ z
        p = z + (rz_new / max(rz, 1e-300)) * p
        rz = rz_new
    return x


def _cross_jac(Y: np.ndarray, g: np.ndarray) -> np.ndarray:
    """J (N, 6) of g . (v + w x Y) with respect to (v, w): [g, Y x g]."""
    return np.concatenate([g, np.cross(Y, g)], axis=1)


# ------------------------------------------------------------------ the estimator

@dataclass(frozen=True)
class MSFConfig:
    segments: int = 300              # SLIC segments of the reference frame
    compactness: float = 10.0        # SLIC: intensity units per grid step
    slic_depth_scale: float = 0.02   # SLIC: metres of depth worth one grid step
    solve_width: int = 160           # finest pyramid level solved: about this wide (px)
    levels: int = 3                  # pyramid levels solved, coarse to fine
    global_levels: int = 0           # the coarsest ones solve one motion increment for all
    iterations: tuple[int, ...] = (3, 2, 2)   # Gauss-Newton steps per level, coarse to fine
    photometric_weight: float = 1.0
    photometric_sigma: float = 2.0   # intensity units (of the high-passed image)
    highpass: float = 3.0            # px: the photometric terms compare I - its local mean over
                                     # the pixels with depth (Gaussian sigma; 0: raw intensity),
                                     # which removes the shading a deforming surface changes
    depth_weight: float = 1.0
    depth_sigma: float = 0.005       # metres
    max_depth_residual: float = 0.1  # m: projective ICP pairs further apart are outliers
    smoothness: float = 0.2          # nu: neighbour rigidity (per pixel of a segment)
    smooth_depth_edge: float = 0.05  # m: neighbours further apart in depth couple less
    huber: float = 1.0               # robust threshold on the normalised residuals
    damping: float = 1e-3            # Levenberg-Marquardt damping (relative to diag)
    reselect_fraction: float = 0.5   # new reference when less of it stays consistent
    # per-pixel refinement of the segments' flow at full resolution (0 iterations: off; needs
    # the photometric term): every first-frame pixel's 3-D point in frame c, Gauss-Newton on
    # photometric + depth-along-the-ray residuals aggregated over a Gaussian window
    refine_iterations: int = 3
    refine_window: float = 3.0       # px: Gaussian sigma of the window
    refine_depth_window: float = 0.7  # px: the depth term's window with noise-free depth (it
                                      # widens to refine_window as the depth noise estimated
                                      # in the first frame, depth_noise(), reaches depth_sigma)
    refine_prior: float = 0.1        # m: sigma of the prior towards the segment's rigid motion

    def check(self) -> None:
        for name in ('refine_iterations',):
            if getattr(self, name) < 0:
                raise ValueError(f'{name}={getattr(self, name)}: expected >= 0')
        for name in ('segments', 'solve_width', 'levels'):
            if getattr(self, name) < 1:
                raise ValueError(f'{name}={getattr(self, name)}: expected >= 1')
        for name in ('compactness', 'slic_depth_scale', 'photometric_sigma', 'depth_sigma',
                     'max_depth_residual', 'smooth_depth_edge', 'huber', 'refine_window',
                     'refine_depth_window', 'refine_prior'):
            if not getattr(self, name) > 0:
                raise ValueError(f'{name}={getattr(self, name)}: expected > 0')
        for name in ('photometric_weight', 'depth_weight', 'smoothness', 'damping', 'highpass'):
            if not getattr(self, name) >= 0:
                raise ValueError(f'{name}={getattr(self, name)}: expected >= 0')
        if self.photometric_weight == 0 and self.depth_weight == 0:
            raise ValueError('photometric_weight, depth_weight: at least one must be > 0')
        if len(self.iterations) < 1 or min(self.iterations) < 0:
            raise ValueError(f'iterations={self.iterations}: expected non-negative counts')
        if not 0 <= self.reselect_fraction < 1:
            raise ValueError(f'reselect_fraction={self.reselect_fraction}: expected [0, 1)')


ICP_CONFIG = MSFConfig(photometric_weight=0.0, smoothness=0.0)   # the per-segment ICP baseline
# (the per-pixel refinement needs the photometric term: with photometric_weight 0 it is off)


@dataclass
class _Level:
    """One pyramid level of a frame."""
    K: np.ndarray
    img: np.ndarray      # (h, w, 3) float32: intensity, d/dx, d/dy
    V: np.ndarray        # (h, w, 3) float32 points (NaN: no depth)
    N: np.ndarray        # (h, w, 3) float32 normals (NaN: unknown)


def _pyramid(gray: np.ndarray, depth: np.ndarray, K: np.ndarray, first: int, n: int,
             hp_sigma: float = 0.0) -> list[_Level]:
    """Levels first .. first+n-1 (level l: every 2^l-th pixel after blurring, K / 2^l); each
    level's photometric image is its :func:`highpass` (``hp_sigma`` pixels of that level)."""
    out = []
    g, z = gray, depth
    for lev in range(first + n):
        if lev >= first:
            Kl = K.copy()
            Kl[:2] /= 2 ** lev
            h = highpass(g, np.isfinite(z), hp_sigma)
            gx = cv2.Sobel(h, cv2.CV_32F, 1, 0, ksize=3, scale=1 / 8)
            gy = cv2.Sobel(h, cv2.CV_32F, 0, 1, ksize=3, scale=1 / 8)
            V = back_project(z, Kl)
            out.append(_Level(Kl, np.dstack([h, gx, gy]), V, _normals(V)))
        g = cv2.GaussianBlur(g, (5, 5), 1.0)[::2, ::2].copy()
        z = z[::2, ::2].copy()
    return out[::-1]   # coarse first


def _normals(V: np.ndarray) -> np.ndarray:
    dx = np.full_like(V, np.nan)
    dy = np.full_like(V, np.nan)
    dx[:, 1:-1] = V[:, 2:] - V[:, :-2]
    dy[1:-1] = V[2:] - V[:-2]
    n = np.cross(dx, dy)
    n /= np.linalg.norm(n, axis=-1, keepdims=True) + 1e-12
    # depth edges: no normal where the neighbours jump by more than 10% of the depth
    jump = np.maximum(np.abs(dx[..., 2]), np.abs(dy[..., 2])) > 0.1 * V[..., 2]
    n[jump] = np.nan
    return n


def _layer_parts(layers: np.ndarray, rad: int) -> list[tuple[tuple[slice, slice], np.ndarray]]:
    """Per depth layer (:func:`depth_layers`) but the largest: its bounding box grown by
    ``rad`` (clipped to the image) and its mask there, (h, w, 1) bool; [] for one layer."""
    n = int(layers.max()) + 1 if layers.size else 0
    if n <= 1:
        return []
    h, w = layers.shape
    big = int(np.argmax(np.bincount(layers[layers >= 0], minlength=n)))
    parts = []
    for k in range(n):
        m = layers == k
        rows, cols = np.nonzero(m.any(1))[0], np.nonzero(m.any(0))[0]
        if k == big or rows.size == 0:
            continue
        box = (slice(max(int(rows[0]) - rad, 0), min(int(rows[-1]) + rad + 1, h)),
               slice(max(int(cols[0]) - rad, 0), min(int(cols[-1]) + rad + 1, w)))
        parts.append((box, m[box][..., None]))
    return parts


def _layered_sum(buf: np.ndarray, parts: list, rad: int, sigma: float) -> np.ndarray:
    """Gaussian-weighted window sums of ``buf`` (h, w, k) float32, each pixel's over the pixels
    of its own depth layer only (``parts``: :func:`_layer_parts` with the same ``rad``, every
    layer but the largest; []: one layer; ``buf`` zero where no layer is); float64.  The
    largest layer's sums are the whole image's less the other layers' (each of those blurred
    over its own box only)."""
    ks = (2 * rad + 1, 2 * rad + 1)
    out = cv2.GaussianBlur(buf, ks, sigma).reshape(buf.shape)
    if not parts:
        return out.astype(np.float64)
    own = []
    for box, m in parts:
        # BORDER_CONSTANT: outside the box is outside the layer (zero), not a replica
        blur = cv2.GaussianBlur(np.where(m, buf[box], np.float32(0)), ks, sigma,
                                borderType=cv2.BORDER_CONSTANT).reshape(m.shape[:2]
                                                                        + buf.shape[2:])
        out[box] -= blur
        own.append((box, m, blur))
    for box, m, blur in own:                       # the smaller layers' own pixels
        np.copyto(out[box], blur, where=m)
    return out.astype(np.float64)


def _segment_slots(seg: np.ndarray, S: int) -> np.ndarray:
    """(S, n_max) indices of each segment's pixels, padded with len(seg) (a zero row)."""
    order = np.argsort(seg, kind='stable')
    cnt = np.bincount(seg, minlength=S)
    start = np.concatenate([[0], np.cumsum(cnt)[:-1]])
    n_max = max(int(cnt.max()) if cnt.size else 0, 1)
    rank = np.arange(seg.size) - np.repeat(start, cnt)
    slots = np.full((S, n_max), seg.size, np.int64)
    slots[seg[order], rank] = order
    return slots


def _skew(a: np.ndarray) -> np.ndarray:
    """[a]x (..., 3, 3) of vectors a (..., 3)."""
    K = np.zeros(a.shape + (3,))
    K[..., 0, 1], K[..., 0, 2], K[..., 1, 2] = -a[..., 2], a[..., 1], -a[..., 0]
    K[..., 1, 0], K[..., 2, 0], K[..., 2, 1] = a[..., 2], -a[..., 1], a[..., 0]
    return K


def _pair_normal_equations(Ya: np.ndarray, Yb: np.ndarray, r: np.ndarray, wH: np.ndarray,
                           wg: np.ndarray) -> tuple[np.ndarray, ...]:
    """Blocks of the neighbour-rigidity term sum_k |r_k|^2, r_k = (T_a P_k - T_b P_k) / sigma,
    in closed form: the Jacobian of T P (+ v + w x T P) is [I, -[Y]x], so J_a^T J_b summed over
    the points is [[n I, -[sum Y_b]x], [[sum Y_a]x, sum (Y_a . Y_b) I - Y_b Y_a^T]].
    Ya, Yb, r (E, k, 3); wH = w / sigma^2, wg = w / sigma (E,).  Returns Haa, Hbb, Hab (E, 6, 6),
    ga, gb (E, 6)."""
    E, k = Ya.shape[:2]
    eye = np.eye(3)
    sa, sb = Ya.sum(1), Yb.sum(1)

    def block(P: np.ndarray, sp_: np.ndarray, Q: np.ndarray, sq: np.ndarray) -> np.ndarray:
        H = np.empty((E, 6, 6))
        H[:, :3, :3] = k * eye
        H[:, :3, 3:] = -_skew(sq)
        H[:, 3:, :3] = _skew(sp_)
        QP = Q[:, 0, :, None] * P[:, 0, None, :]
        for j in range(1, k):
            QP += Q[:, j, :, None] * P[:, j, None, :]
        H[:, 3:, 3:] = (QP[:, 0, 0] + QP[:, 1, 1] + QP[:, 2, 2])[:, None, None] * eye - QP
        H *= wH[:, None, None]
        return H
    Haa, Hbb = block(Ya, sa, Ya, sa), block(Yb, sb, Yb, sb)
    Hab = block(Ya, sa, Yb, sb)
    Hab *= -1
    rs = r.sum(1)
    ga = np.concatenate([rs, np.cross(Ya, r).sum(1)], 1) * wg[:, None]
    gb = np.concatenate([rs, np.cross(Yb, r).sum(1)], 1) * -wg[:, None]
    return Haa, Hbb, Hab, ga, gb


def _hessian_pattern(S: int, pairs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """CSR structure of the 6S x 6S normal equations: 6x6 diagonal blocks, then per pair the
    (a, a), (b, b), (a, b) and (b, a) blocks, in that order; returns, for every value of that
    order, its slot in the CSR data, and the CSR indices and indptr."""
    o6 = np.arange(6)
    pa, pb = pairs[:, 0], pairs[:, 1]
    seg = np.arange(S)
    rows, cols = [], []
    for A_, B_ in ((seg, seg), (pa, pa), (pb, pb), (pa, pb), (pb, pa)):
        rows.append(np.broadcast_to(A_[:, None, None] * 6 + o6[None, :, None],
                                    (len(A_), 6, 6)).ravel())
        cols.append(np.broadcast_to(B_[:, None, None] * 6 + o6[None, None, :],
                                    (len(B_), 6, 6)).ravel())
    key = np.concatenate(rows) * (6 * S) + np.concatenate(cols)
    uniq, slot = np.unique(key, return_inverse=True)
    indptr = np.concatenate([[0], np.cumsum(np.bincount(uniq // (6 * S), minlength=6 * S))])
    return slot.ravel(), (uniq % (6 * S)).astype(np.int32), indptr.astype(np.int32)


@dataclass
class _Ref:
    """A reference frame: its segments and, per solved level, the pixels used."""
    labels: np.ndarray                    # (H, W) full resolution, -1: no depth
    X: np.ndarray                         # (H, W, 3) full-resolution points
    S: int
    pairs: np.ndarray                     # (E, 2)
    pair_w: np.ndarray                    # (E,)
    pair_pts: np.ndarray                  # (E, 3, 3): 3 points per pair (reference frame)
    hp: np.ndarray                        # (H, W) the photometric image (highpass)
    layers: np.ndarray | None = None      # (H, W) its depth layers (depth_layers)
    # per level: (X (N,3), I (N,), seg (N,), slots (S, n_max) of each segment's pixels (N: none),
    # photometric ok (N,): away from the image border)
    level_pix: list = field(default_factory=list)
    index: int = 0
    hess: tuple | None = None             # the 6S x 6S pattern: (slot of each value, indices,
                                          # indptr), values ordered diag, aa, bb, ab, ba blocks
    inc: tuple | None = None              # (S x E) incidence of pairs' first / second segment


@dataclass
class MSFFrame:
    flow: np.ndarray          # (H, W, 3) float32 camera-frame flow X_c - X_ref0 (NaN: unknown)
    valid: np.ndarray         # (H, W) bool
    consistent: float         # fraction of the current reference's pixels consistent in c
    reselected: bool          # this frame became the new reference
    seconds: float


class MSF:
    """Multi-frame scene flow from the first frame given to :meth:`step` to every later one."""

    def __init__(self, K: np.ndarray, config: MSFConfig | None = None) -> None:
        self.K = _check_K(K)
        self.cfg = config or MSFConfig()
        self.cfg.check()
        self._ref: _Ref | None = None
        self._R = self._t = None
        # chaining through re-selected references: per first-frame pixel, its current point in
        # the active reference's camera frame at the time that reference was taken
        self._X0: np.ndarray | None = None        # (H, W, 3) first-frame points
        self._Y_in_ref: np.ndarray | None = None  # (H, W, 3)
        self._seg_of0: np.ndarray | None = None   # (H, W) active-ref segment of each pixel
        # first-frame pixels with depth: flat indices, points (N, 3), photometric values (N,)
        # (the refinement works on their bounding box: slices, points, photometric values)
        self._pix0: tuple[tuple[slice, slice], np.ndarray, np.ndarray, np.ndarray] | None = None
        self._depth_noise = 0.0                   # m, of the first frame (depth_noise)
        self.reselections: list[int] = []
        self._frame = -1

    # ---------------------------------------------------------------- public
    def step(self, image: np.ndarray, depth: np.ndarray) -> MSFFrame | None:
        """Add a frame; returns None for the first one (the reference), else its flow."""
        t0 = time.perf_counter()
        gray, z = to_gray(image), depth_metres(depth)
        if gray.shape != z.shape:
            raise ValueError(f'image: size {gray.shape} differs from depth {z.shape}')
        if not np.isfinite(z).any():            # nothing to back-project (a covered sensor)
            raise ValueError('depth: no valid pixel (every one NaN, inf, 0 or negative)')
        self._frame += 1
        if self._ref is None:
            if self._X0 is not None and gray.shape != self._X0.shape[:2]:
                raise ValueError('image: size changed')
            self._set_reference(gray, z)
            self._X0 = self._ref.X.copy()
            self._Y_in_ref = self._X0.copy()
            self._seg_of0 = self._ref.labels.copy()
            ok = np.isfinite(self._X0).all(-1)
            self._depth_noise = depth_noise(z)
            if ok.any():
                rad = int(np.ceil(2.5 * self.cfg.refine_window))
                ys, xs = np.nonzero(ok.any(1))[0], np.nonzero(ok.any(0))[0]
                box = (slice(max(int(ys[0]) - rad, 0), int(ys[-1]) + rad + 1),
                       slice(max(int(xs[0]) - rad, 0), int(xs[-1]) + rad + 1))
                self._pix0 = (box, self._X0[box].copy(), self._ref.hp[box].copy(),
                              self._ref.layers[box].copy())
            return None
        if gray.shape != self._ref.labels.shape:
            raise ValueError(f'image: size {gray.shape} differs from the reference '
                             f'{self._ref.labels.shape}')
        hp = layered_highpass(gray, depth_layers(z, self.cfg.smooth_depth_edge),
                              self.cfg.highpass)
        levels = _pyramid(gray, z, self.K, self._first_level(gray.shape[1]), self.cfg.levels,
                          self.cfg.highpass)
        consistent = self._solve(levels)
        # first-frame pixels -> this frame, through the active reference's segment motions
        seg = self._seg_of0
        ok = seg >= 0
        Y = np.full(self._X0.shape, np.nan, np.float32)
        s = seg[ok]
        Y[ok] = np.einsum('nij,nj->ni', self._R[s], self._Y_in_ref[ok]) + self._t[s]
        if self.cfg.refine_iterations > 0 and self.cfg.photometric_weight > 0:
            Y = self._refine(Y, hp, z)
        flow = Y - self._X0
        valid = np.isfinite(flow).all(-1)
        reselect = consistent < self.cfg.reselect_fraction
        if reselect:
            self._reselect(gray, z, Y)
        return MSFFrame(flow=flow, valid=valid, consistent=consistent, reselected=reselect,
                        seconds=time.perf_counter() - t0)

    # ---------------------------------------------------------------- internals
    def _margin(self) -> float:
        """Full-resolution pixels from the image border where the photometric image is not
        compared: the high-pass's local mean there depends on what lies beyond the border."""
        return float(np.ceil(2 * self.cfg.highpass)) if self.cfg.highpass > 0 else 0.0

    def _first_level(self, width: int) -> int:
        return max(0, int(round(np.log2(max(width / self.cfg.solve_width, 1.0)))))

    def _set_reference(self, gray: np.ndarray, z: np.ndarray) -> None:
        c = self.cfg
        labels = slic(gray, z, c.segments, c.compactness, c.slic_depth_scale)
        layers = depth_layers(z, c.smooth_depth_edge)
        hp = layered_highpass(gray, layers, c.highpass)
        X = back_project(z, self.K)
        S = int(labels.max()) + 1
        pairs, blen = segment_graph(labels)
        ok = labels >= 0
        lab = labels[ok]
        cnt = np.maximum(np.bincount(lab, minlength=S), 1).astype(np.float64)
        cen = np.stack([np.bincount(lab, X[ok][:, k], S) for k in range(3)], 1) / cnt[:, None]
        # three points per pair: both centroids and one off the line joining them
        a, b = cen[pairs[:, 0]], cen[pairs[:, 1]]
        mid = 0.5 * (a + b)
        d = b - a
        off = np.cross(d, [0.0, 0.0, 1.0])
        off += np.where(np.linalg.norm(off, axis=1, keepdims=True) < 1e-9, [[1.0, 0, 0]], 0)
        off *= (0.5 * np.linalg.norm(d, axis=1) / (np.linalg.norm(off, axis=1) + 1e-12))[:, None]
        pts = np.stack([a, b, mid + off], 1) if len(pairs) else np.empty((0, 3, 3))
        dz = np.abs(a[:, 2] - b[:, 2])
        w = 1.0 / (1.0 + (dz / c.smooth_depth_edge) ** 2)
        ref = _Ref(labels, X, S, pairs, w, pts, hp, layers=layers, index=self._frame)
        ref.hess = _hessian_pattern(S, pairs if c.smoothness > 0 else pairs[:0])
        E = len(pairs)
        ref.inc = tuple(sp.csr_matrix((np.ones(E), (pairs[:, k], np.arange(E))), shape=(S, E))
                        for k in (0, 1))
        lev_first = self._first_level(gray.shape[1])
        for L in _pyramid(gray, z, self.K, lev_first, c.levels, c.highpass):
            lev = int(round(np.log2(self.K[0, 0] / L.K[0, 0])))
            sl = labels[::2 ** lev, ::2 ** lev]
            m = (sl >= 0) & np.isfinite(L.V[..., 2])
            if lev == lev_first:              # the finest level: a checkerboard of pixels
                yy_, xx_ = np.mgrid[:m.shape[0], :m.shape[1]]
                m &= (yy_ + xx_) % 2 == 0
            segp = sl[m].astype(np.int64)
            A = _segment_slots(segp, S)
            hl, wl = sl.shape
            mg = self._margin()                  # level pixels (the high-pass is per level)
            yy, xx = np.nonzero(m)
            pok = (xx >= mg) & (xx <= wl - 1 - mg) & (yy >= mg) & (yy <= hl - 1 - mg)
            ref.level_pix.append((L.V[m].astype(np.float64), L.img[..., 0][m].astype(np.float64),
                                  segp, A, pok))
        self._ref = ref
        self._R = np.repeat(np.eye(3)[None], S, axis=0)
        self._t = np.zeros((S, 3))

    def _solve(self, levels: list[_Level]) -> float:
        c = self.cfg
        its = list(c.iterations) + [c.iterations[-1]] * max(0, len(levels) - len(c.iterations))
        consistent = 0.0
        for li, L in enumerate(levels):
            X, I0, seg, A, pok = self._ref.level_pix[li]
            tau = c.max_depth_residual * (2.0 ** (len(levels) - 1 - li)) ** 0.5
            common = li < c.global_levels
            for _ in range(its[li]):
                consistent = self._gn_step(L, X, I0, seg, A, pok, tau, common=common)
            if its[li] == 0:
                consistent = self._gn_step(L, X, I0, seg, A, pok, tau, update=False)
        return consistent

    def _gn_step(self, L: _Level, X: np.ndarray, I0: np.ndarray, seg: np.ndarray,
                 A: np.ndarray, pok: np.ndarray, tau: float, update: bool = True,
                 common: bool = False
                 ) -> float:
        """One damped Gauss-Newton step of every segment's pose (``common``: one increment
        shared by all, left-multiplied); returns the fraction of depth-consistent pixels."""
        c = self.cfg
        S = self._ref.S
        h, w = L.V.shape[:2]
        fx, fy, cx, cy = L.K[0, 0], L.K[1, 1], L.K[0, 2], L.K[1, 2]
        Y = np.einsum('nij,nj->ni', self._R[seg], X) + self._t[seg]
        z = np.maximum(Y[:, 2], 1e-6)
        iz = 1.0 / z
        u, v = fx * Y[:, 0] * iz + cx, fy * Y[:, 1] * iz + cy
        inside = (Y[:, 2] > 1e-6) & (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
        # projective point-to-plane ICP
        iu = np.clip(np.rint(np.where(inside, u, 0)), 0, w - 1).astype(np.int64)
        iv = np.clip(np.rint(np.where(inside, v, 0)), 0, h - 1).astype(np.int64)
        Q = L.V[iv, iu].astype(np.float64)
        n = L.N[iv, iu].astype(np.float64)
        d = Y - Q
        okD = inside & np.isfinite(n).all(1) & np.isfinite(Q[:, 2])
        okD &= np.where(okD, np.einsum('ij,ij->i', d, d), np.inf) < tau * tau
        consistent = float(okD.sum()) / max(X.shape[0], 1) if X.shape[0] else 0.0
        if not update:
            return consistent
        # both data terms over all pixels, zero weight where unused; per segment
        # sum w J^T J and sum w J r as batched products over its pixels (slots A)
        N = X.shape[0]
        Jw = np.zeros((2, N + 1, 7))                 # sqrt(w) [J | r], depth then photometric
        if c.depth_weight > 0 and okD.any():
            nd = np.where(okD[:, None], n, 0.0)
            r = np.einsum('ij,ij->i', nd, np.where(okD[:, None], d, 0.0)) / c.depth_sigma
            J = _cross_jac(Y, nd) / c.depth_sigma
            wt = c.depth_weight * okD * np.minimum(1.0, c.huber / np.maximum(np.abs(r), 1e-12))
            sw = np.sqrt(wt)[:, None]
            Jw[0, :N, :6] = J * sw
            Jw[0, :N, 6] = r * sw[:, 0]
        mg = self._margin()
        okI = inside & pok & (u >= mg) & (u <= w - 1 - mg) & (v >= mg) & (v <= h - 1 - mg)
        if c.photometric_weight > 0 and okI.any():
            smp = _bilinear(L.img, u, v)
            r = (smp[:, 0] - I0) / c.photometric_sigma
            gx, gy = smp[:, 1] * fx * iz, smp[:, 2] * fy * iz
            g = np.stack([gx, gy, -(gx * Y[:, 0] + gy * Y[:, 1]) * iz], 1) / c.photometric_sigma
            J = _cross_jac(Y, g)
            wt = c.photometric_weight * okI * np.minimum(1.0, c.huber / np.maximum(
                np.abs(r), 1e-12))
            sw = np.sqrt(wt)[:, None]
            Jw[1, :N, :6] = J * sw
            Jw[1, :N, 6] = r * sw[:, 0]
        G = Jw[:, A].reshape(2 * A.shape[0], A.shape[1], 7)    # (2S, n_max, 7)
        M = np.matmul(G.transpose(0, 2, 1), G)
        M = M[:A.shape[0]] + M[A.shape[0]:]
        Hs = M[:, :6, :6]                             # (S, 6, 6)
        bs = M[:, :6, 6]
        if common:
            Hg, bg = Hs.sum(0), bs.sum(0)
            dg = np.diag(Hg)
            step = -np.linalg.solve(Hg + c.damping * np.diag(dg) + (1e-9 + 1e-6 * dg.max())
                                    * np.eye(6), bg)
            Rd = _exp_so3(step[None, 3:])[0]
            self._R = Rd @ self._R
            self._t = self._t @ Rd.T + step[:3]
            return consistent
        diag = np.einsum('sii->si', Hs)
        # damping: relative to the diagonal, plus a floor for segments with little data
        floor = 1e-6 + 1e-3 * np.median(diag[diag > 0]) if (diag > 0).any() else 1.0
        Hd = Hs + (c.damping * diag[:, :, None] * np.eye(6) + floor * np.eye(6))
        vals = [Hd.ravel()]
        blocks = Hd                                      # the preconditioner's 6x6 blocks
        b = bs
        P = self._ref.pairs
        if c.smoothness > 0 and len(P):
            npix = np.bincount(seg, minlength=S).astype(np.float64)
            pa, pb = P[:, 0], P[:, 1]
            wp = c.smoothness * self._ref.pair_w * np.sqrt(npix[pa] * npix[pb]) / 3.0
            pts = self._ref.pair_pts                      # (E, 3, 3)
            Ya = np.einsum('eij,ekj->eki', self._R[pa], pts) + self._t[pa][:, None]
            Yb = np.einsum('eij,ekj->eki', self._R[pb], pts) + self._t[pb][:, None]
            r = (Ya - Yb) / c.depth_sigma                 # (E, 3, 3)
            Haa, Hbb, Hab, ga, gb = _pair_normal_equations(Ya, Yb, r, wp / c.depth_sigma ** 2,
                                                           wp / c.depth_sigma)
            Ia, Ib = self._ref.inc
            b = b + Ia @ ga + Ib @ gb
            blocks = blocks + (Ia @ Haa.reshape(-1, 36) + Ib @ Hbb.reshape(-1, 36)
                               ).reshape(S, 6, 6)
            vals += [Haa.ravel(), Hbb.ravel(), Hab.ravel(),
                     np.transpose(Hab, (0, 2, 1)).ravel()]
        slot, indices, indptr = self._ref.hess
        vals = np.concatenate(vals)
        data = np.bincount(slot[:vals.size], weights=vals, minlength=indices.size)
        Hm = sp.csr_matrix((data, indices, indptr), shape=(6 * S, 6 * S))
        # an inexact step: 8 preconditioned CG iterations (relative residual 1e-2) cost a fifth
        # of a converged solve and, measured, were as accurate (flag: better with the occluder)
        delta = -_block_pcg(Hm, b.ravel(), blocks, iterations=8, tol=1e-2).reshape(S, 6)
        delta[~np.isfinite(delta).all(1)] = 0.0
        Rd = _exp_so3(delta[:, 3:])
        self._R = Rd @ self._R
        self._t = np.einsum('sij,sj->si', Rd, self._t) + delta[:, :3]
        return consistent

    def _refine(self, Y: np.ndarray, hp: np.ndarray, z: np.ndarray) -> np.ndarray:
        """Per-pixel refinement of Y (H, W, 3), the first-frame pixels' points in this frame
        predicted by their segments' motions.  Unknown: each pixel's displacement D = Y - X0.
        Residuals: photometric (hp at pi(Y) - hp0) and depth along the ray (Y_z - z(pi(Y))),
        Huber-weighted; their normal equations, linearised at each pixel's own D, are averaged
        over a Gaussian window (Lucas-Kanade in 3-D: a locally constant displacement), plus a
        weak prior towards the rigid prediction, which is all that is left where the pixel is
        out of the image or behind a nearer surface (the rigid prediction's depth test).  The
        windows sum over the pixel's own depth layer of the first frame (:func:`depth_layers`:
        not what is behind a silhouette); a sample near a depth edge of this frame has no
        photometric nor depth term (its Sobel Jacobians straddle the edge); along the ray a
        point keeps within RAY_CLAMP x ``max_depth_residual`` of its rigid prediction.
        Dense float32 arrays over the first frame's bounding box."""
        c = self.cfg
        if self._pix0 is None:
            return Y
        H, W = z.shape
        box, X, I0, layers = self._pix0
        Yr = Y[box]
        ok = np.isfinite(Yr).all(-1) & np.isfinite(X).all(-1)
        if not ok.any():
            return Y
        h, w = ok.shape
        oy, ox = box[0].start, box[1].start
        X = np.where(ok[..., None], X, 0).astype(np.float32)
        Dr = np.where(ok[..., None], Yr - X, 0).astype(np.float32)
        fx, fy, cx, cy = (np.float32(a) for a in (self.K[0, 0], self.K[1, 1], self.K[0, 2],
                                                  self.K[1, 2]))
        known = np.isfinite(z)
        zf = np.where(known, z, 0).astype(np.float32)
        edges = depth_edges(z, c.smooth_depth_edge)
        nodepth = cv2.dilate(((~known) | edges).astype(np.uint8), np.ones((3, 3), np.uint8))
        nearedge = cv2.dilate(edges.astype(np.uint8), np.ones((3, 3), np.uint8))

        def sobel(a: np.ndarray, dx: int, dy: int) -> np.ndarray:
            return cv2.Sobel(a, cv2.CV_32F, dx, dy, ksize=3, scale=1 / 8)
        exact = np.dstack([hp, zf])                  # sampled with exact weights
        approx = np.dstack([sobel(hp, 1, 0), sobel(hp, 0, 1), sobel(zf, 1, 0), sobel(zf, 0, 1),
                            nodepth.astype(np.float32), nearedge.astype(np.float32)])
        # Jacobians and masks: cv2's bilinear

        def project(P: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
            iz = 1 / np.maximum(P[..., 2], np.float32(1e-6))
            u, v = fx * P[..., 0] * iz + cx, fy * P[..., 1] * iz + cy
            inside = ok & (P[..., 2] > 1e-6) & (u >= 0) & (u <= W - 1) & (v >= 0) & (v <= H - 1)
            return u, v, iz, inside
        u, v, _, vis = project(X + Dr)
        iu = np.clip(np.rint(np.where(vis, u, 0)), 0, W - 1).astype(np.int64)
        iv = np.clip(np.rint(np.where(vis, v, 0)), 0, H - 1).astype(np.int64)
        vis &= ~(zf[iv, iu] < (X + Dr)[..., 2] - c.max_depth_residual) | ~known[iv, iu]
        mg = self._margin()
        py, px = np.mgrid[oy:oy + h, ox:ox + w]
        vis_I = vis & (px >= mg) & (px <= W - 1 - mg) & (py >= mg) & (py <= H - 1 - mg)
        wp = np.float32(1.0 / c.refine_prior ** 2)
        D = Dr.copy()
        ray = X / np.maximum(np.linalg.norm(X, axis=-1, keepdims=True), np.float32(1e-9))
        sI, sD = np.float32(c.photometric_sigma), np.float32(c.depth_sigma)
        rad = int(np.ceil(2.5 * c.refine_window))
        hub = np.float32(c.huber)
        buf = np.empty((h, w, 9), np.float32)
        bufD = np.empty((h, w, 9), np.float32)
        # the depth term's window: narrow with clean depth (it fixes the point along its ray
        # by itself, and a wide window there biases it where the surface bends along the ray),
        # as wide as the photometric one once the estimated depth noise reaches depth_sigma
        winD = float(np.clip(c.refine_window * self._depth_noise / c.depth_sigma,
                             min(c.refine_depth_window, c.refine_window), c.refine_window))
        radD = int(np.ceil(2.5 * winD))
        parts, partsD = _layer_parts(layers, rad), _layer_parts(layers, radD)
        for _ in range(c.refine_iterations):
            P = X + D
            u, v, iz, inside = project(P)
            inside &= vis
            uf, vf = u.ravel(), v.ravel()
            ex = _bilinear(exact, uf, vf).reshape(h, w, 2)
            ap = cv2.remap(approx, u, v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            xz, yz = P[..., 0] * iz, P[..., 1] * iz
            gxf, gyf = ap[..., 0] * (fx / sI) * iz, ap[..., 1] * (fy / sI) * iz
            JI = (gxf, gyf, -(gxf * xz + gyf * yz))
            rI = (ex[..., 0] - I0) / sI
            dxf, dyf = ap[..., 2] * (fx / sD) * iz, ap[..., 3] * (fy / sD) * iz
            JD = (-dxf, -dyf, 1 / sD + dxf * xz + dyf * yz)
            rD = (P[..., 2] - ex[..., 1]) / sD
            okI = inside & vis_I & (u >= mg) & (u <= W - 1 - mg) & (v >= mg) & (v <= H - 1 - mg)
            okI &= ap[..., 5] < 1e-3
            wI = (c.photometric_weight * okI) * np.minimum(1, hub / np.maximum(np.abs(rI), 1e-12))
            okD = inside & (ap[..., 4] < 1e-3) & (np.abs(rD) * sD < c.max_depth_residual)
            wD = (c.depth_weight * okD) * np.minimum(1, hub / np.maximum(np.abs(rD), 1e-12))
            wI = np.where(np.isfinite(rI), wI, 0).astype(np.float32)
            wD = np.where(np.isfinite(rD), wD, 0).astype(np.float32)
            rI, rD = np.nan_to_num(rI), np.nan_to_num(rD)
            tI = wI * (JI[0] * D[..., 0] + JI[1] * D[..., 1] + JI[2] * D[..., 2] - rI)
            tD = wD * (JD[0] * D[..., 0] + JD[1] * D[..., 1] + JD[2] * D[..., 2] - rD)
            k = 0
            for i in range(3):
                wJi, wJd = wI * JI[i], wD * JD[i]
                for j in range(i, 3):
                    buf[..., k] = wJi * JI[j]
                    bufD[..., k] = wJd * JD[j]
                    k += 1
                buf[..., 6 + i] = tI * JI[i]
                bufD[..., 6 + i] = tD * JD[i]
            agg = _layered_sum(buf, parts, rad, c.refine_window)
            agg += _layered_sum(bufD, partsD, radD, winD)
            a00, a01, a02, a11, a12, a22 = (agg[..., i] for i in range(6))
            a00, a11, a22 = a00 + wp, a11 + wp, a22 + wp
            b = agg[..., 6:] + wp * Dr
            c00, c01, c02 = a11 * a22 - a12 * a12, a02 * a12 - a01 * a22, a01 * a12 - a02 * a11
            c11, c12, c22 = a00 * a22 - a02 * a02, a01 * a02 - a00 * a12, a00 * a11 - a01 * a01
            det = a00 * c00 + a01 * c01 + a02 * c02
            D = (np.stack([c00 * b[..., 0] + c01 * b[..., 1] + c02 * b[..., 2],
                           c01 * b[..., 0] + c11 * b[..., 1] + c12 * b[..., 2],
                           c02 * b[..., 0] + c12 * b[..., 1] + c22 * b[..., 2]], -1)
                 / det[..., None]).astype(np.float32)
        # beside a silhouette before a background, or in a sensor's hole, a window may hold no
        # depth term, and then nothing fixes a point along its ray (the photometric term
        # cannot): further from its segment's rigid motion along the ray than the segment
        # solve's own outlier distance (x RAY_CLAMP) it keeps that motion's depth there
        along = np.einsum('...i,...i->...', D - Dr, ray)
        far = np.abs(along) > RAY_CLAMP * c.max_depth_residual
        D = np.where(far[..., None], D - along[..., None] * ray, D)
        out = Y.copy()
        out[box] = np.where(ok[..., None], X + D, Y[box])
        return out

    def _reselect(self, gray: np.ndarray, z: np.ndarray, Y: np.ndarray) -> None:
        """Frame c becomes the reference: every first-frame pixel is handed to the new segment
        it lands on where the depth agrees, else to the new segment most of its old segment's
        pixels landed on (or it keeps its last position if none)."""
        old_seg = self._seg_of0
        self._set_reference(gray, z)
        self.reselections.append(self._frame)
        new_lab = self._ref.labels
        H, W = new_lab.shape
        ok = np.isfinite(Y).all(-1) & (old_seg >= 0)
        zz = np.where(ok, Y[..., 2], 1.0)
        u = np.rint(self.K[0, 0] * Y[..., 0] / zz + self.K[0, 2])
        v = np.rint(self.K[1, 1] * Y[..., 1] / zz + self.K[1, 2])
        inside = ok & (u >= 0) & (u <= W - 1) & (v >= 0) & (v <= H - 1)
        iu = np.clip(np.nan_to_num(u), 0, W - 1).astype(int)
        iv = np.clip(np.nan_to_num(v), 0, H - 1).astype(int)
        lab_at = np.where(inside, new_lab[iv, iu], -1)
        zt = np.where(inside, z[iv, iu], np.nan)
        hit = (lab_at >= 0) & (np.abs(zt - Y[..., 2]) < self.cfg.max_depth_residual)
        # majority new segment per old segment
        S_old = int(old_seg.max()) + 1
        votes = sp.coo_matrix((np.ones(int(hit.sum())), (old_seg[hit], lab_at[hit])),
                              shape=(S_old, self._ref.S)).tocsr()
        has = np.asarray(votes.sum(1)).ravel() > 0
        major = np.where(has, np.asarray(votes.argmax(1)).ravel(), -1)
        seg = np.where(hit, lab_at, np.where(ok, major[np.maximum(old_seg, 0)], -1))
        self._seg_of0 = seg.astype(np.int32)
        self._Y_in_ref = np.where(ok[..., None], Y, np.nan).astype(np.float64)
        self._R = np.repeat(np.eye(3)[None], self._ref.S, axis=0)
        self._t = np.zeros((self._ref.S, 3))


def msf_sequence(images: Sequence[np.ndarray], depths: Sequence[np.ndarray], K: np.ndarray,
                 config: MSFConfig | None = None) -> tuple[np.ndarray, np.ndarray, dict]:
    """Flow (F-1, H, W, 3) float32 from the first frame to each later one (first frame's
    camera frame; NaN where unknown), valid (F-1, H, W) and stats (wall and CPU seconds per
    frame after the reference, re-selected references, and ``skipped``: (frame, error) of every
    later frame the estimator rejected, e.g. one without valid depth: its flow NaN, not valid).
    A reference frame it rejects is a ValueError."""
    if len(images) != len(depths) or len(images) < 2:
        raise ValueError(f'images, depths: expected the same number (>= 2) of frames, got '
                         f'{len(images)} and {len(depths)}')
    est = MSF(K, config)
    flows, valids, secs, cpu = [], [], [], []
    t0 = time.perf_counter()
    est.step(images[0], depths[0])
    ref_s = time.perf_counter() - t0
    skipped: list[tuple[int, str]] = []
    shape = est._X0.shape                      # (H, W, 3), set by the reference frame
    for i, (img, d) in enumerate(zip(images[1:], depths[1:]), 1):
        c0 = time.process_time()
        try:
            fr = est.step(img, d)
        except ValueError as err:                # reported, the sequence goes on
            skipped.append((i, str(err)))
            flows.append(np.full(shape, np.nan, np.float32))
            valids.append(np.zeros(shape[:2], bool))
            continue
        cpu.append(time.process_time() - c0)
        flows.append(fr.flow)
        valids.append(fr.valid)
        secs.append(fr.seconds)
    return (np.stack(flows), np.stack(valids),
            {'seconds_per_frame': float(np.mean(secs)) if secs else float('nan'),
             'cpu_seconds_per_frame': float(np.mean(cpu)) if cpu else float('nan'),
             'reference_seconds': ref_s, 'reselections': list(est.reselections),
             'skipped': skipped})


# ------------------------------------------------------------------ baseline

def dis_depth_flow(images: Sequence[np.ndarray], depths: Sequence[np.ndarray], K: np.ndarray,
                   preset: str = 'medium') -> tuple[np.ndarray, np.ndarray, dict]:
    """Baseline: DIS optical flow first frame -> each frame (seeded by the previous one), the
    matched pixel back-projected with that frame's depth.  Same outputs as msf_sequence."""
    presets = {'ultrafast': cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST,
               'fast': cv2.DISOPTICAL_FLOW_PRESET_FAST,
               'medium': cv2.DISOPTICAL_FLOW_PRESET_MEDIUM}
    if preset not in presets:
        raise ValueError(f'preset={preset!r}: expected one of {list(presets)}')
    K = _check_K(K)
    dis = cv2.DISOpticalFlow_create(presets[preset])
    dis.setUseSpatialPropagation(True)
    g0 = np.clip(to_gray(images[0]), 0, 255).astype(np.uint8)
    z0 = depth_metres(depths[0])
    X0 = back_project(z0, K)
    H, W = g0.shape
    gx, gy = np.meshgrid(np.arange(W, dtype=np.float32), np.arange(H, dtype=np.float32))
    flows, valids, secs, cpu = [], [], [], []
    prev = None
    for img, d in zip(images[1:], depths[1:]):
        t0, c0 = time.perf_counter(), time.process_time()
        g = np.clip(to_gray(img), 0, 255).astype(np.uint8)
        of = dis.calc(g0, g, None if prev is None else prev.copy())   # seeded by the last
        prev = of
        u, v = gx + of[..., 0], gy + of[..., 1]
        inside = (u >= 0) & (u <= W - 1) & (v >= 0) & (v <= H - 1)
        iu = np.clip(np.rint(u), 0, W - 1).astype(int)
        iv = np.clip(np.rint(v), 0, H - 1).astype(int)
        z = depth_metres(d)[iv, iu]
        Y = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], -1)
        fl = np.where(inside[..., None], Y, np.nan) - X0
        flows.append(fl.astype(np.float32))
        valids.append(np.isfinite(fl).all(-1))
        secs.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return np.stack(flows), np.stack(valids), {'seconds_per_frame': float(np.mean(secs)),
                                               'cpu_seconds_per_frame': float(np.mean(cpu))}


def with_config(config: MSFConfig | None, **changes: object) -> MSFConfig:
    return replace(config or MSFConfig(), **changes)
