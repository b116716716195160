"""The checks of the tracking parameters, one per name: ``MFOFConfig.validate``,
``ReferenceFlowTracker`` and the tracker node's ``params.TrackerParams`` all use these, so the
core and the ROS parameters accept exactly the same values.  Each rule is a function of the
value returning None or the reason it is invalid (a NaN is never valid)."""
from __future__ import annotations

import math
import numbers
from collections.abc import Callable
from typing import Any

import cv2

PRESETS = {
    'ultrafast': cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST,
    'fast': cv2.DISOPTICAL_FLOW_PRESET_FAST,
    'medium': cv2.DISOPTICAL_FLOW_PRESET_MEDIUM,
}
MASKS = ('texture', 'full')     # which reference pixels are tracked: textured ones or all

Rule = Callable[[Any], 'str | None']


def _number(v: Any) -> bool:
    return isinstance(v, numbers.Real) and not isinstance(v, bool) and math.isfinite(v)


def _one_of(values: Any) -> Rule:
    allowed = sorted(values)
    return lambda v: None if isinstance(v, str) and v in allowed else f'expected one of {allowed}'


def _at_least(n: int) -> Rule:
    return lambda v: None if _number(v) and v >= n else f'must be >= {n}'


def _positive(v: Any) -> str | None:
    return None if _number(v) and v > 0 else 'must be > 0'


def _non_negative(v: Any) -> str | None:
    return None if _number(v) and v >= 0 else 'must be >= 0'


def _fraction(v: Any) -> str | None:
    return None if _number(v) and 0 <= v < 1 else 'must be in [0, 1)'


PARAM_RULES: dict[str, Rule] = {
    'preset': _one_of(PRESETS),
    'recapture_finest_scale': _at_least(-1),
    'backward_preset': _one_of(PRESETS),
    'mask': _one_of(MASKS),
    'stride': _at_least(1),
    'min_std': _non_negative,
    'rank': _at_least(0),
    'batch_rank': _at_least(0),
    'window': _at_least(3),
    'refine_every': _at_least(1),
    'reselect_patience': _at_least(1),
    'spatial_sigma': _non_negative,
    'subspace_weight': _non_negative,
    'temporal_weight': _non_negative,
    'fb_threshold': _positive,
    'ncc_threshold': _positive,
    'huber_px': _positive,
    'outlier_px': _non_negative,
    'recapture_margin': _non_negative,
    'chain_check_px': _non_negative,
    'support_radius': _at_least(0),
    'support_fraction': _fraction,
    'lk_radius': _at_least(0),
    'lk_iterations': _at_least(1),
    'fusion_gap_px': _non_negative,
    'reselect_fraction': _fraction,
    'collapse_fraction': _fraction,
    'occlusion_threshold': _positive,
}


def check_param(name: str, value: Any) -> None:
    """Raise ValueError naming the parameter and the value when ``PARAM_RULES`` rejects it."""
    reason = PARAM_RULES[name](value)
    if reason:
        raise ValueError(f'{name}={value!r}: {reason}')
