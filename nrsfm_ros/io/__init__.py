"""Message and bag conversion: ROS messages <-> NumPy, bags, synthetic sequences, export."""
