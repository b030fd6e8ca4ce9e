"""uav_vs.vision."""
