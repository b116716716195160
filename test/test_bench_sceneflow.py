"""bench/bench_sceneflow.py's RGB-D cases: the structured-light sensor model (``--sensor
kinect``) and the wall behind the surface (``--background on``) at a given ``--distance``."""
from __future__ import annotations

import sys

import numpy as np
import pytest
from tests_helpers import bench_module


@pytest.fixture
def bench(monkeypatch):
    yield bench_module(monkeypatch, 'bench_sceneflow')
    sys.modules.pop('bench_sceneflow', None)


def test_kinect_depth_is_quantised_noisy_and_has_holes(bench):
    K = np.array([[300.0, 0, 79.5], [0, 300.0, 59.5], [0, 0, 1]])
    v, u = np.mgrid[0:120, 0:160]
    z = (1.5 + 0.002 * (u - 80)).astype(np.float32)[None].repeat(2, axis=0)  # a slanted plane
    z[:, :, 150:] = np.nan                                                 # off the surface
    out = bench.kinect_depth(z, K, np.random.default_rng(0))
    assert out.shape == z.shape and out.dtype == np.float32
    on = np.isfinite(z)
    holes = on & ~np.isfinite(out)
    assert 0.02 <= holes.mean() / on.mean() <= 0.2 and not np.isfinite(out[~on]).any()
    d8 = 43.5 / out[np.isfinite(out)] * 8                  # disparity in 1/8 px: integers
    assert np.abs(d8 - np.rint(d8)).max() < 1e-2
    err = (out - z)[np.isfinite(out)]
    assert 0.5 * 1.425e-3 * 1.5 ** 2 < err.std() < 3 * 1.425e-3 * 1.5 ** 2 + 0.006


def test_run_case_with_the_wall_and_the_sensor_model(bench):
    rows = bench.run_case('flag', (96, 72), False, 'kinect', 3, background=True, distance=1.5)
    assert [r['method'] for r in rows] == ['zero', 'DIS+depth', 'segment ICP', 'MSF']
    for r in rows:
        assert r['background'] is True and r['distance'] == 1.5 and r['sensor'] == 'kinect'
        assert np.isfinite(r['epe_m']) and r['epe_m'] > 0
    assert rows[1]['vs_dis'] == 1.0
