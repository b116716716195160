"""rclpy nodes: thin wrappers of the processors in nrsfm_ros.processing."""
