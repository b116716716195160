"""3D scene flow: the definition (:mod:`.definition`), NRSfM-Flow between consecutive
reconstructions (:mod:`.nrsfm_flow`) and RGB-D MSF with piecewise rigid motion (:mod:`.msf`)."""
from .definition import FRAMES, camera_to_object, epe, relative_motion
from .msf import MSF, ICP_CONFIG, MSFConfig, MSFFrame, dis_depth_flow, msf_sequence
from .nrsfm_flow import SceneFlow, scene_flow

__all__ = ['FRAMES', 'ICP_CONFIG', 'MSF', 'MSFConfig', 'MSFFrame', 'SceneFlow', 'camera_to_object',
           'dis_depth_flow', 'epe', 'msf_sequence', 'relative_motion', 'scene_flow']
