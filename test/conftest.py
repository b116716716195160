"""Test setup: loopback-only DDS with a per-run domain, paths to the shared benchmark data."""
from __future__ import annotations

import os
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
SHARED = ROOT.parent / 'shared'

os.environ.setdefault('FASTRTPS_DEFAULT_PROFILES_FILE', str(ROOT / 'config' /
                                                            'fastdds_loopback.xml'))
os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
os.environ.pop('NRSFM_DDS', None)     # the tests' own graphs stay on loopback
os.environ.setdefault('ROS_DOMAIN_ID', str(10 + os.getpid() % 90))


def shared_data(*parts: str) -> Path:
    path = SHARED.joinpath('data', *parts)
    if not path.exists():
        pytest.skip(f'shared data {path} not present')
    return path


@pytest.fixture
def rclpy_context():
    import rclpy
    ctx = rclpy.context.Context()
    rclpy.init(context=ctx)
    yield ctx
    rclpy.try_shutdown(context=ctx)
