"""uav_vs.control."""
