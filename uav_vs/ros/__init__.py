"""uav_vs.ros."""
