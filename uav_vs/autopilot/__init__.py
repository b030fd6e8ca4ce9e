"""uav_vs.autopilot."""
