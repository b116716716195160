"""Pure algorithms on NumPy arrays: no ROS, no files, no printing, no globals."""
