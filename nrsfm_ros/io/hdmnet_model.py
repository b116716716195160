"""HDM-Net at run time: the shipped ONNX model (``nrsfm_ros/models/hdmnet.onnx``, made by
``nrsfm-ros train-hdmnet``; its ``hdmnet.json`` beside it) through ONNX Runtime, with the NumPy
pre- and post-processing of ``core.hdmnet``."""
from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from ..core import hdmnet as H

MODEL_DIR = Path(__file__).resolve().parent.parent / 'models'
DEFAULT_MODEL = MODEL_DIR / 'hdmnet.onnx'


class HDMNetModel:
    """``predict(rgb, K)`` -> :class:`core.hdmnet.HDMNetResult`.  ``threads``: ONNX Runtime's
    intra-op threads (the issue's budget: 2 cores)."""

    def __init__(self, path: str | Path | None = None, threads: int = 2) -> None:
        import onnxruntime as ort
        self.path = Path(path) if path is not None else DEFAULT_MODEL
        if not self.path.is_file():
            raise FileNotFoundError(f'HDM-Net model {self.path} does not exist')
        if threads < 1:
            raise ValueError(f'threads={threads}: expected >= 1')
        meta_path = self.path.with_suffix('.json')
        self.meta: dict[str, Any] = json.loads(meta_path.read_text()) if meta_path.is_file() \
            else {}
        opts = ort.SessionOptions()
        opts.intra_op_num_threads = threads
        opts.inter_op_num_threads = 1
        opts.log_severity_level = 3
        # no busy-waiting of idle worker threads between frames: on a loaded 2-core machine
        # they starve the pre/post-processing (and the rest of the node) of CPU
        opts.add_session_config_entry('session.intra_op.allow_spinning', '0')
        try:
            self.session = ort.InferenceSession(str(self.path), opts,
                                                providers=['CPUExecutionProvider'])
        except Exception as err:  # noqa: BLE001 -- onnxruntime raises its own types
            raise ValueError(f'HDM-Net model {self.path}: not a loadable ONNX model '
                             f'({err})') from err
        inp = self.session.get_inputs()[0]
        out = self.session.get_outputs()[0]
        want_in, want_out = [1, 3, H.INPUT_SIZE, H.INPUT_SIZE], [1, H.GRID, H.GRID, 3]
        if list(inp.shape) != want_in or list(out.shape) != want_out:
            raise ValueError(f'HDM-Net model {self.path}: input {inp.shape} / output '
                             f'{out.shape}, expected {want_in} / {want_out}')
        self._in, self._out = inp.name, out.name
        self.last_K: np.ndarray | None = None

    def raw(self, x: np.ndarray) -> np.ndarray:
        """The network alone: (1, 3, INPUT_SIZE, INPUT_SIZE) float32 -> (GRID, GRID, 3)."""
        return self.session.run([self._out], {self._in: x})[0][0]

    def predict(self, image: np.ndarray, K: np.ndarray | None = None) -> H.HDMNetResult:
        """rgb8 image (H, W, 3) uint8 and optional intrinsics (3, 3) -> the grid in the
        camera frame (``core.hdmnet.postprocess``); ``last_K`` is the K used."""
        t0 = time.perf_counter()
        x, canon = H.preprocess(image)
        t1 = time.perf_counter()
        grid = self.raw(x)
        t2 = time.perf_counter()
        self.last_K = H.default_K(canon) if K is None else np.asarray(K, np.float64)
        pts = H.postprocess(grid, canon, self.last_K)
        valid = np.isfinite(pts).all(axis=-1)
        return H.HDMNetResult(pts, valid, (t2 - t1) * 1e3, (time.perf_counter() - t0) * 1e3)
