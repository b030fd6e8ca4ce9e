"""uav_vs.nodes."""
