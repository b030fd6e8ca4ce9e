"""uav_vs: visual servoing for UAVs on ROS 2 Jazzy."""
