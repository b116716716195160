"""Dense 2D point tracking (reference frame -> every frame)."""
from .reference_flow import PRESETS, ReferenceFlowTracker, TrackFrame, texture_mask

__all__ = ['PRESETS', 'ReferenceFlowTracker', 'TrackFrame', 'texture_mask']
