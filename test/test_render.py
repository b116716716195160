"""Readable renders (nrsfm_ros.render, `nrsfm-ros evaluate --render`): the per-point error is
metric B's, the heat map puts an injected error where it was injected, panels are not blank and
the reconstruction panel shows the reconstruction, videos hold one frame per ground-truth frame,
a frame takes well under a second, and the CLI flags work and fail cleanly."""
from __future__ import annotations

import time

import cv2
import numpy as np
import pytest

from nrsfm_ros import render
from nrsfm_ros.cli import main
from nrsfm_ros.core.metrics import frame_alignment, frame_e3d, point_errors
from nrsfm_ros.io import pointcloud2 as pc2
from nrsfm_ros.io.bag import BagWriter
from nrsfm_ros.io.msgtypes import RosbagsFactory

SIZE = render.PANEL_PX
HOT = 0.9                     # heat map: "hottest" colours, value >= HOT x vmax


def sheet(F: int = 4, nx: int = 60, ny: int = 40, seed: int = 0) -> np.ndarray:
    """A waving sheet (F, nx*ny, 3) 4 m in front of the camera, 1 m x 0.7 m."""
    x, y = np.meshgrid(np.linspace(-0.5, 0.5, nx), np.linspace(-0.35, 0.35, ny))
    x, y = x.ravel(), y.ravel()
    S = []
    for f in range(F):
        z = 4.0 + 0.08 * np.sin(3 * x + 0.6 * f) + 0.05 * np.cos(4 * y - 0.3 * f)
        S.append(np.stack([x, y, z], axis=1))
    return np.asarray(S)


def similar(X: np.ndarray, seed: int = 1) -> np.ndarray:
    """X moved by a random rotation, scale and shift (what metric B's alignment undoes)."""
    rng = np.random.default_rng(seed)
    Q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    return 2.5 * X @ Q + rng.normal(size=3)


def region(X: np.ndarray) -> np.ndarray:
    """The disc of points (radius 0.12 m about x=0.2, y=0.1) an error is injected into."""
    return np.hypot(X[:, 0] - 0.2, X[:, 1] - 0.1) < 0.12


def heat_values(img: np.ndarray) -> np.ndarray:
    """Per pixel: the heat value t in [0, 1] of its inferno colour (NaN: background or a
    colour far from the inferno scale)."""
    lut = render.heat(np.linspace(0, 1, 256), 1.0).astype(np.float64)
    px = img.reshape(-1, 3).astype(np.float64)
    d = ((px[:, None, :] - lut[None]) ** 2).sum(axis=2)
    t = np.argmin(d, axis=1) / 255.0
    t[(d.min(axis=1) > 30) | (px == render.BACKGROUND).all(axis=1)] = np.nan
    return t.reshape(img.shape[:2])


def panels(img: np.ndarray) -> list[np.ndarray]:
    """The three panels of a compare image, without their title strips."""
    return [img[render.HEADER_PX:, k * SIZE:(k + 1) * SIZE] for k in range(3)]


def filled(p: np.ndarray) -> float:
    """Fraction of pixels not background (by more than video compression changes it)."""
    d = np.abs(p.astype(int) - np.array(render.BACKGROUND)).max(axis=2)
    return float((d > 12).mean())


def test_point_errors_are_metric_b():
    gt = sheet(1)[0]
    rng = np.random.default_rng(3)
    X = similar(gt + 0.01 * rng.normal(size=gt.shape))
    X[:, 0] *= -1                                        # a reflection: allowed, as in metric B
    e = point_errors(X, gt)
    assert np.sqrt(np.mean(e ** 2)) == pytest.approx(frame_e3d(X, gt), rel=1e-9)
    aligned = frame_alignment(X, gt).apply(X)
    assert np.abs(aligned - gt).max() < 0.06              # the similarity is undone
    assert np.abs(X - gt).max() > 1.0


def test_heat_map_marks_the_injected_error():
    gt = sheet(1)[0]
    ids = np.arange(gt.shape[0])
    bad = region(gt)
    moved = gt.copy()
    moved[bad, 2] -= 0.15                                # the region pushed towards the camera
    fe = render.frame_errors(similar(moved), ids, gt, ids)
    assert np.nanargmax(fe.error) in np.flatnonzero(bad)
    assert np.median(fe.error[bad]) > 5 * np.median(fe.error[~bad])
    vmax = float(np.percentile(fe.error, render.ERROR_PERCENTILE))
    view = render.orbit_view(gt.mean(axis=0), 0.62)
    hot = panels(render.compare_image(fe, gt, view, 'normals', vmax))[2]
    t = heat_values(hot[:SIZE - 40])                     # above the colour bar
    assert np.isfinite(t).mean() > 0.2
    # where the hottest pixels are: the injected region, seen from the same view
    mask = render.splat(view, fe.aligned[bad], np.zeros((bad.sum(), 3), np.uint8), 0.02)
    mask = cv2.dilate((mask[:SIZE - 40] == 0).all(axis=2).astype(np.uint8), np.ones((5, 5)))
    hottest = np.nan_to_num(t, nan=0) >= HOT
    assert hottest.sum() > 50
    assert mask[hottest].mean() > 0.97
    # the same cloud without the injected error, on the same scale: nothing is hot
    fe0 = render.frame_errors(similar(gt), ids, gt, ids)
    t0 = heat_values(panels(render.compare_image(fe0, gt, view, 'normals', vmax))[2][:SIZE - 40])
    assert (np.nan_to_num(t0, nan=0) >= HOT).sum() == 0
    assert np.isfinite(t0).mean() > 0.2


def test_depth_shading_runs_near_to_far():
    gt = sheet(1)[0]
    view = render.orbit_view(gt.mean(axis=0), 0.62)
    c = render.shade(view, view.eye + np.outer([view.near, view.far], view.R[2]), None, 'depth')
    turbo = cv2.applyColorMap(np.array([[255], [0]], np.uint8), cv2.COLORMAP_TURBO)[:, 0]
    assert (c == turbo).all()                            # near: the red end, far: the blue end
    with pytest.raises(ValueError, match="shading='flat'"):
        render.shade(view, gt, None, 'flat')


@pytest.mark.parametrize('shading', render.SHADINGS)
def test_compare_panels_are_readable(tmp_path, shading):
    S = sheet(4)
    ids = np.arange(S.shape[1]) + 100
    exact = {f: (similar(S[f], f), ids) for f in range(4)}
    rr = render.render_stream(exact, S, ids, tmp_path / 'exact', shading=shading,
                              video='none', stills=[2], vmax=0.1)
    assert rr.stills == [tmp_path / 'exact' / 'compare_002.png'] and rr.video is None
    rec, gt, hot = panels(cv2.imread(str(rr.stills[0])))
    for p in (rec, gt, hot):
        assert filled(p) > 0.15                          # not blank
    # the reconstruction panel shows the reconstruction: identical to the ground truth's when
    # it is exact, and not when it is another frame's shape
    other = {2: (similar(S[0]), ids)}
    wrong = render.render_stream(other, S, ids, tmp_path / 'wrong', shading=shading,
                                 video='none', stills=[2], vmax=0.1)
    rec_w = panels(cv2.imread(str(wrong.stills[0])))[0]
    diff = np.abs(rec.astype(int) - gt.astype(int)).mean()
    diff_w = np.abs(rec_w.astype(int) - gt.astype(int)).mean()
    assert diff < 1.0 and diff_w > 3 * max(diff, 1.0)


@pytest.mark.parametrize('video', ['gif', 'mp4'])
def test_video_has_a_frame_per_ground_truth_frame(tmp_path, video):
    S = sheet(5)
    ids = np.arange(S.shape[1])
    clouds = {f: (similar(S[f]), ids) for f in (0, 1, 3)}      # no cloud for frames 2 and 4
    rr = render.render_stream(clouds, S, ids, tmp_path, video=video, fps=5.0)
    assert rr.video == tmp_path / f'stream.{video}' and rr.frames == 5
    assert rr.stills == [tmp_path / f'compare_{f:03d}.png' for f in (0, 1, 3)]
    if video == 'gif':
        from PIL import Image, ImageSequence
        with Image.open(rr.video) as gif:
            assert gif.n_frames == 5 and gif.info['duration'] == 200
            assert gif.size == (round(3 * SIZE * render.GIF_SCALE),
                                round((SIZE + render.HEADER_PX) * render.GIF_SCALE))
            frames = [np.asarray(fr.convert('RGB'))[:, :, ::-1]
                      for fr in ImageSequence.Iterator(gif)]
    else:
        cap = cv2.VideoCapture(str(rr.video))
        frames = []
        while True:
            ok, img = cap.read()
            if not ok:
                break
            frames.append(img)
        assert len(frames) == 5
    # frame 2 has no cloud: its reconstruction panel is empty, frame 1's is not
    scale = frames[0].shape[1] / (3 * SIZE)
    third = int(frames[0].shape[1] / 3)
    top = int(render.HEADER_PX * scale) + 2
    assert filled(frames[2][top:, :third]) < 0.05 < 0.1 < filled(frames[1][top:, :third])
    still = render.render_stream(clouds, S, ids, tmp_path / 's', video='none', stills=[2])
    assert filled(panels(cv2.imread(str(still.stills[0])))[0]) < 0.05


def test_render_is_fast_on_a_demo_sized_cloud(tmp_path):
    S = sheet(3, 96, 64)                                  # 6144 points, the demo's size
    ids = np.arange(S.shape[1])
    clouds = {f: (similar(S[f]), ids) for f in range(3)}
    t = time.perf_counter()
    rr = render.render_stream(clouds, S, ids, tmp_path, video='gif')
    assert rr.seconds_per_frame < 1.0
    assert (time.perf_counter() - t) / 3 < 1.0           # video encoding included


def test_gif_without_pillow_is_one_clear_error(tmp_path, monkeypatch):
    import sys
    monkeypatch.setitem(sys.modules, 'PIL', None)
    with pytest.raises(RuntimeError, match='a GIF needs Pillow'):
        render.write_video(tmp_path / 'x.gif', [np.zeros((8, 8, 3), np.uint8)], 10.0)


def test_bad_arguments_name_the_value(tmp_path):
    S = sheet(2)
    ids = np.arange(S.shape[1])
    clouds = {0: (S[0], ids)}
    with pytest.raises(ValueError, match="video='avi'"):
        render.render_stream(clouds, S, ids, tmp_path, video='avi')
    with pytest.raises(ValueError, match=r'stills: frame\(s\) \[7\]'):
        render.render_stream(clouds, S, ids, tmp_path, stills=[7])
    with pytest.raises(ValueError, match='no cloud has a ground-truth frame'):
        render.render_stream({9: (S[0], ids)}, S, ids, tmp_path)


def write_output_bag(path, S, ids, stamps, displaced_frame=None, rgb=None):
    """An output bag as process would write it: nrsfm/points clouds of S (x, y, z, track_id,
    and rgb (P, 3) uint8 packed when given)."""
    fac = RosbagsFactory()
    with BagWriter(path) as w:
        for f, st in enumerate(stamps):
            X = similar(S[f], f).astype(np.float32)
            if f == displaced_frame:
                X = similar(np.where(region(S[f])[:, None], S[f] - [0, 0, 0.15], S[f]),
                            f).astype(np.float32)
            cols = {'x': X[:, 0], 'y': X[:, 1], 'z': X[:, 2]}
            if rgb is not None:
                cols['rgb'] = pc2.pack_rgb(rgb)
            cols['track_id'] = ids.astype(np.uint32)
            msg = pc2.to_msg(cols, fac, int(st), 'camera_optical_frame')
            w.write('nrsfm/points', 'sensor_msgs/msg/PointCloud2', msg, int(st))


def test_evaluate_render_flags(tmp_path, capsys):
    F = 4
    S = sheet(F)
    ids = np.arange(S.shape[1]) * 2 + 7
    stamps = 1_700_000_000 * 10 ** 9 + np.arange(F) * 10 ** 8
    np.savez(tmp_path / 'gt.npz', S=S, track_ids=ids, stamps_ns=stamps, fps=np.array(10.0))
    write_output_bag(tmp_path / 'out', S, ids, stamps, displaced_frame=2)
    argv = ['evaluate', str(tmp_path / 'out'), '--ground-truth', str(tmp_path / 'gt.npz')]
    capsys.readouterr()
    assert main([*argv, '--render', str(tmp_path / 'r')]) == 0
    out = capsys.readouterr().out
    assert f'and {tmp_path / "r" / "stream.gif"} ({F} frames)' in out
    from PIL import Image
    with Image.open(tmp_path / 'r' / 'stream.gif') as gif:
        assert gif.n_frames == F
    # stills: first, middle, last; the displaced frame 2 shows the hottest heat map
    names = sorted(p.name for p in (tmp_path / 'r').glob('compare_*.png'))
    assert names == ['compare_000.png', 'compare_002.png', 'compare_003.png']
    hot = [(np.nan_to_num(heat_values(panels(cv2.imread(str(tmp_path / 'r' / n)))[2][
        :SIZE - 40]), nan=0) >= HOT).sum() for n in names]
    assert hot[1] > 50 and hot[0] == hot[2] == 0
    assert main([*argv, '--render', str(tmp_path / 'd'), '--shading', 'depth',
                 '--video', 'none']) == 0
    assert not (tmp_path / 'd' / 'stream.gif').exists()
    depth = panels(cv2.imread(str(tmp_path / 'd' / 'compare_000.png')))[0]
    normals = panels(cv2.imread(str(tmp_path / 'r' / 'compare_000.png')))[0]
    assert np.abs(depth.astype(int) - normals.astype(int)).mean() > 10     # other shading
    assert main([*argv, '--render', str(tmp_path / 'm'), '--video', 'mp4']) == 0
    assert cv2.VideoCapture(str(tmp_path / 'm' / 'stream.mp4')).get(
        cv2.CAP_PROP_FRAME_COUNT) == F
    capsys.readouterr()
    assert main([*argv, '--shading', 'depth']) == 2
    err = capsys.readouterr().err
    assert err.startswith('error: --shading and --video') and err.count('\n') == 1


def test_export_renders_in_perspective_with_the_clouds_colours(tmp_path, capsys):
    S = sheet(2)
    ids = np.arange(S.shape[1])
    stamps = 10 ** 18 + np.arange(2) * 10 ** 8
    rgb = np.zeros((S.shape[1], 3), np.uint8)
    rgb[:, 0] = 200                                       # every point red
    rgb[region(S[0]), 2] = 200                            # the disc magenta
    write_output_bag(tmp_path / 'c', S, ids, stamps, rgb=rgb)
    write_output_bag(tmp_path / 'p', S, ids, stamps)
    assert main(['export', str(tmp_path / 'c'), '--out', str(tmp_path / 'ec')]) == 0
    assert main(['export', str(tmp_path / 'p'), '--out', str(tmp_path / 'ep')]) == 0
    img = cv2.imread(str(tmp_path / 'ec' / 'cloud_0000.png'))
    cloud = (img != np.array(render.BACKGROUND, np.uint8)).any(axis=2)
    assert 0.1 < cloud.mean() < 0.9
    b, g, r = (img[cloud][:, k].astype(int) for k in range(3))
    assert (r == 200).mean() > 0.95 and (g == 0).mean() > 0.95
    magenta = (b == 200).mean()
    assert 0.02 < magenta < 0.2                           # the disc, a few % of the sheet
    plain = cv2.imread(str(tmp_path / 'ep' / 'cloud_0001.png'))
    assert filled(plain) > 0.1 and len(np.unique(plain.reshape(-1, 3), axis=0)) > 20  # depth
    with pytest.raises(ValueError, match=r'rgb: expected shape \(2400, 3\)'):
        render.render_cloud(tmp_path / 'x.png', S[0], rgb[:5])
