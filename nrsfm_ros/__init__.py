"""nrsfm_ros: dense monocular non-rigid 3D reconstruction and point set alignment for ROS 2."""

__version__ = '0.1.0'
