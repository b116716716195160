"""3D scene flow between consecutive reconstructions."""
from .nrsfm_flow import SceneFlow, scene_flow

__all__ = ['SceneFlow', 'scene_flow']
