"""rclpy nodes: thin wrappers of the processors in nrsfm_ros.processing."""
from __future__ import annotations

import faulthandler
import os
import signal

# A node process started by the launcher (live.Graph sets this) that is stopped with Ctrl-C
# while it is still importing exits cleanly (code 0) instead of with a KeyboardInterrupt
# traceback: the signal is only remembered (raising inside an import can break it: an
# interrupted C-extension import of NumPy fails with ImportError), and spin_node returns 0 before
# starting rclpy; it restores the default handler before rclpy takes over.
LAUNCHED_ENV = 'NRSFM_NODE_PROCESS'
STOP_REQUESTED = []         # non-empty once Ctrl-C came during startup


def _stop_during_startup(signum: int, frame: object) -> None:
    STOP_REQUESTED.append(signum)


if os.environ.get(LAUNCHED_ENV) == '1':
    signal.signal(signal.SIGINT, _stop_during_startup)
    # SIGUSR1 prints every thread's stack to stderr: live.Graph sends it to a node that does
    # not stop on Ctrl-C before it kills it, so the log says where the node hung
    faulthandler.register(signal.SIGUSR1, all_threads=True)
