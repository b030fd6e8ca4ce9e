"""uav_vs.bag."""
