"""uav_vs.sim."""
