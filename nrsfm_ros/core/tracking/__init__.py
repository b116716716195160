"""Dense 2D point tracking (reference frame -> every frame).

``MFOFTracker`` (default): multi-frame subspace flow with an occlusion tensor, streaming with
windowed refinement; ``track_sequence`` adds a two-sided batch pass.  ``ReferenceFlowTracker``:
plain DIS reference->frame seeded by the previous frame (the baseline)."""
from .mfof import MFOFConfig, MFOFFrame, MFOFTracker, TrackResult, track_sequence
from .reference_flow import ReferenceFlowTracker, TrackFrame, texture_mask
from .rules import MASKS, PARAM_RULES, PRESETS, check_param

__all__ = ['MASKS', 'PARAM_RULES', 'PRESETS', 'MFOFConfig', 'MFOFFrame', 'MFOFTracker',
           'ReferenceFlowTracker', 'TrackFrame', 'TrackResult', 'check_param', 'texture_mask',
           'track_sequence']
