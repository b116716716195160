"""The live graph across two hosts, on one machine: two network namespaces joined by a private
veth pair (10.231.0.1 <-> 10.231.0.2, nothing else in them but lo, so nothing can leave the
machine), DDS over UDP on the veth only (no shared memory across the namespaces), discovery
by ROS_AUTOMATIC_DISCOVERY_RANGE=SUBNET with ROS_STATIC_PEERS naming the other host, and
NRSFM_DDS=network so the launcher and the CLI keep those settings.  Host A runs the registrar
through the graph launcher (--nodes registrar); host B replays its input with `nrsfm-ros
replay` (a reference and moving clouds) and receives what comes back (test/sub_aligned.py).
The namespaces are deleted in the fixture's teardown.  Needs root and `ip netns` (skipped
otherwise)."""
from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from nrsfm_ros.io import pointcloud2 as pc2
from nrsfm_ros.io.bag import BagWriter
from nrsfm_ros.io.msgtypes import RosbagsFactory
from nrsfm_ros.live import ensure_loopback_env

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
HOSTS = {'a': '10.231.0.1', 'b': '10.231.0.2'}
CLOUDS = 12
POINTS = 400

PROFILE = """<?xml version="1.0" encoding="UTF-8" ?>
<!-- this host's DDS: UDPv4 on its veth address only, no shared memory -->
<profiles xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">
  <transport_descriptors>
    <transport_descriptor>
      <transport_id>udp_veth</transport_id>
      <type>UDPv4</type>
      <interfaceWhiteList><address>{address}</address></interfaceWhiteList>
    </transport_descriptor>
  </transport_descriptors>
  <participant profile_name="veth_only" is_default_profile="true">
    <rtps>
      <userTransports><transport_id>udp_veth</transport_id></userTransports>
      <useBuiltinTransports>false</useBuiltinTransports>
    </rtps>
  </participant>
</profiles>
"""


def _ip(*args: str, check: bool = True) -> subprocess.CompletedProcess:
    return subprocess.run(['ip', *args], capture_output=True, text=True, check=check,
                          timeout=20)


def _netns_unavailable() -> str:
    if os.geteuid() != 0:
        return 'network namespaces need root'
    if shutil.which('ip') is None:
        return 'iproute2 (ip) is not installed'
    r = subprocess.run(['ip', 'netns', 'list'], capture_output=True, text=True, timeout=20)
    if r.returncode != 0:
        return f'ip netns unavailable: {r.stderr.strip()}'
    return ''


@pytest.fixture
def hosts(tmp_path):
    """Two namespaces 'a' and 'b' with a veth pair created inside them (it never exists in
    this machine's own namespace), lo up; yields {host: (namespace, address, profile)}."""
    why = _netns_unavailable()
    if why:
        pytest.skip(why)
    tag = f'{os.getpid() % 100000}'
    ns = {h: f'nrsfm{tag}{h}' for h in HOSTS}
    dev = {h: f'nv{tag}{h}' for h in HOSTS}
    made: list[str] = []
    try:
        for h in HOSTS:
            _ip('netns', 'add', ns[h])
            made.append(ns[h])
        _ip('link', 'add', dev['a'], 'netns', ns['a'], 'type', 'veth', 'peer', 'name',
            dev['b'], 'netns', ns['b'])
        out = {}
        for h, address in HOSTS.items():
            _ip('-n', ns[h], 'addr', 'add', f'{address}/30', 'dev', dev[h])
            _ip('-n', ns[h], 'link', 'set', 'lo', 'up')
            _ip('-n', ns[h], 'link', 'set', dev[h], 'up')
            profile = tmp_path / f'fastdds_{h}.xml'
            profile.write_text(PROFILE.format(address=address))
            out[h] = (ns[h], address, profile)
        end = time.monotonic() + 10      # carrier on both ends (Fast DDS filters out a
        while not all('LOWER_UP' in _ip('-n', ns[h], '-o', 'link', 'show', dev[h]).stdout
                      for h in HOSTS):   # whitelisted interface that is not running yet)
            assert time.monotonic() < end, 'the veth pair did not come up'
            time.sleep(0.05)
        yield out
    finally:
        for name in made:
            for pid in _ip('netns', 'pids', name, check=False).stdout.split():
                try:                        # only what this test started runs in there
                    os.kill(int(pid), signal.SIGKILL)
                except ProcessLookupError:
                    pass
            _ip('netns', 'del', name, check=False)
        left = _ip('netns', 'list', check=False).stdout
        assert not any(name in left for name in made), left


def _env(hosts: dict, host: str, domain: int) -> dict[str, str]:
    _, address, profile = hosts[host]
    peer = next(a for h, a in HOSTS.items() if h != host)
    env = {k: v for k, v in os.environ.items()
           if not k.startswith(('ROS_', 'FASTRTPS_', 'FASTDDS_'))}
    env.update(NRSFM_DDS='network', ROS_DOMAIN_ID=str(domain),
               ROS_AUTOMATIC_DISCOVERY_RANGE='SUBNET', ROS_STATIC_PEERS=peer,
               FASTRTPS_DEFAULT_PROFILES_FILE=str(profile), RMW_IMPLEMENTATION='rmw_fastrtps_cpp',
               PYTHONPATH=str(ROOT))
    return env


def _in(hosts: dict, host: str, *cmd: str) -> list[str]:
    return ['ip', 'netns', 'exec', hosts[host][0], sys.executable, *cmd]


def _rotation(deg_z: float, deg_x: float) -> np.ndarray:
    a, b = np.radians(deg_z), np.radians(deg_x)
    Rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    Rx = np.array([[1, 0, 0], [0, np.cos(b), -np.sin(b)], [0, np.sin(b), np.cos(b)]])
    return Rz @ Rx


def _input_bag(path: Path) -> tuple[np.ndarray, list[np.ndarray]]:
    """registration/reference X (an anisotropic blob, 2 m in front) at t=0, then CLOUDS
    rigidly moved copies at 10 Hz from t=1.5 s."""
    rng = np.random.default_rng(7)
    X = (rng.normal(size=(POINTS, 3)) * [0.3, 0.15, 0.06] + [0, 0, 2]).astype(np.float32)
    ids = np.arange(POINTS, dtype=np.uint32)
    fac = RosbagsFactory()
    moved = []
    t0 = 10 ** 9

    def msg(P: np.ndarray, st: int):
        return pc2.to_msg({'x': P[:, 0], 'y': P[:, 1], 'z': P[:, 2], 'track_id': ids}, fac, st,
                          'cam')
    with BagWriter(path) as w:
        w.write('registration/reference', 'sensor_msgs/msg/PointCloud2', msg(X, t0), t0)
        for i in range(CLOUDS):
            R = _rotation(1.5 * (i + 1), 0.8 * (i + 1))
            P = ((X - [0, 0, 2]) @ R.T + [0, 0, 2] + [0.01 * i, -0.005 * i, 0.02]
                 ).astype(np.float32)
            moved.append(P)
            st = t0 + 1_500_000_000 + i * 100_000_000
            w.write('nrsfm/points', 'sensor_msgs/msg/PointCloud2', msg(P, st), st)
    return X, moved


def test_graph_across_two_namespaces_over_the_veth(hosts, tmp_path):
    domain = 10 + (os.getpid() + 37) % 90
    links = _ip('-n', hosts['a'][0], '-o', 'link').stdout
    assert [ln.split(':')[1].strip().split('@')[0] for ln in links.splitlines()] == \
        ['lo', f'nv{os.getpid() % 100000}a']            # nothing but lo and the veth
    X, moved = _input_bag(tmp_path / 'input')
    log = tmp_path / 'graph.log'            # the launcher's and the registrar's stderr
    with open(log, 'w') as f:
        graph = subprocess.Popen(_in(hosts, 'a', '-m', 'nrsfm_ros.launch', '--nodes',
                                     'registrar', '--max-restarts', '0'),
                                 env=_env(hosts, 'a', domain), stdout=subprocess.DEVNULL,
                                 stderr=f)

    def graph_log() -> str:
        return log.read_text()[-2000:]
    sub = None
    try:
        # B: a subscriber to the registrar's output; the input is replayed once it has matched
        # the registrar's publisher across the veth (then nothing published is lost)
        sub = subprocess.Popen(_in(hosts, 'b', str(HERE / 'sub_aligned.py'),
                                   str(tmp_path / 'aligned.npz'), str(CLOUDS), '90'),
                               env=_env(hosts, 'b', domain), stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True)
        said = []                       # Fast DDS may log to stdout before 'ready'
        while True:
            line = sub.stdout.readline() if sub.stdout else ''
            said.append(line.strip())
            if not line or line.strip() == 'ready':       # '': it exited
                break
        assert said[-1] == 'ready', (said, sub.stderr.read()[-2000:], graph_log())
        replay = subprocess.run(_in(hosts, 'b', '-m', 'nrsfm_ros.cli', 'replay',
                                    str(tmp_path / 'input'), '--wait-for-subscribers', '1',
                                    '--wait-timeout', '60'),
                                env=_env(hosts, 'b', domain), capture_output=True, text=True,
                                timeout=120)
        assert replay.returncode == 0, (replay.stderr[-2000:], graph_log())
        out, err_text = sub.communicate(timeout=60)
        assert sub.returncode == 0 and f'received {CLOUDS}' in out, (
            out, err_text[-2000:], replay.stdout[-2000:], graph_log())
        assert graph.poll() is None, graph_log()                     # registrar still up
    finally:
        for p in (sub, graph):
            if p is not None and p.poll() is None:
                p.send_signal(signal.SIGINT)
                try:
                    p.wait(20)
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait()
    assert graph.returncode == 0, graph_log()                # clean stop on Ctrl-C
    with np.load(tmp_path / 'aligned.npz') as z:
        aligned = [z[f'arr_{i}'] for i in range(CLOUDS)]
    # the registrar moved every cloud back onto the reference (rows keep the input order)
    err = [float(np.sqrt(((A - X) ** 2).sum(axis=1).mean())) for A in aligned]
    before = [float(np.sqrt(((P - X) ** 2).sum(axis=1).mean())) for P in moved]
    assert max(err) < 0.1 * min(before), (err, before)


def test_network_mode_keeps_the_given_discovery():
    env = {'NRSFM_DDS': 'network', 'ROS_STATIC_PEERS': '10.0.0.2'}
    out = ensure_loopback_env(env)
    assert out['ROS_AUTOMATIC_DISCOVERY_RANGE'] == 'SUBNET'
    assert 'FASTRTPS_DEFAULT_PROFILES_FILE' not in out and 'ROS_DOMAIN_ID' not in out
    assert out['ROS_STATIC_PEERS'] == '10.0.0.2'
    loop = ensure_loopback_env({})
    assert loop['ROS_AUTOMATIC_DISCOVERY_RANGE'] == 'LOCALHOST'
    assert loop['FASTRTPS_DEFAULT_PROFILES_FILE'].endswith('fastdds_loopback.xml')
    with pytest.raises(ValueError, match="NRSFM_DDS='lan': expected one of loopback, network"):
        ensure_loopback_env({'NRSFM_DDS': 'lan'})
    with pytest.raises(ValueError, match='ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST'):
        ensure_loopback_env({'NRSFM_DDS': 'network',
                             'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST'})


@pytest.mark.parametrize('mode, want', [
    ('network', 'SUBNET||'),                 # discovery as given, no loopback profile/domain
    ('', 'LOCALHOST|fastdds_loopback.xml|set'),
])
def test_ros_env_script_honours_network_mode(mode, want):
    env = {k: v for k, v in os.environ.items()
           if not k.startswith(('ROS_', 'FASTRTPS_', 'NRSFM_DDS'))}
    if mode:
        env['NRSFM_DDS'] = mode
    out = subprocess.run(
        ['bash', '-c', '. launch_scripts/ros_env.sh; echo "$ROS_AUTOMATIC_DISCOVERY_RANGE|'
         '${FASTRTPS_DEFAULT_PROFILES_FILE##*/}|${ROS_DOMAIN_ID:+set}"'],
        cwd=ROOT, env=env, capture_output=True, text=True, timeout=20).stdout.strip()
    assert out == want


@pytest.mark.parametrize('env, text', [
    ({'NRSFM_DDS': 'lan'}, "NRSFM_DDS='lan': expected one of loopback, network"),
    ({'NRSFM_DDS': 'network', 'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST'},
     'set SUBNET (or unset it)'),
])
def test_bad_dds_mode_one_error_line_cli_and_launcher(env, text):
    base = {k: v for k, v in os.environ.items() if k != 'NRSFM_DDS'}
    for cmd in (['-m', 'nrsfm_ros.cli', 'topic', 'list', '--seconds', '0.1'],
                ['-m', 'nrsfm_ros.launch', '--nodes', 'registrar']):
        r = subprocess.run([sys.executable, *cmd], env={**base, **env}, capture_output=True,
                           text=True, timeout=60, cwd=ROOT)
        assert r.returncode == 2, (cmd, r.stderr[-2000:])
        lines = r.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith('error:') and text in lines[0], r.stderr
