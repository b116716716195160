"""nrsfm_ros: dense monocular non-rigid 3D reconstruction and point set alignment for ROS 2."""
import os as _os

# One BLAS thread per process unless the user chose otherwise (set before NumPy loads it): the
# solves are many small products, and two OpenBLAS threads on 2 cores cost up to 7x the CPU
# time and 10x the reconstructor's flush time (measured; launch_scripts/ros_env.sh does the same).
_os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')

__version__ = '0.1.0'
