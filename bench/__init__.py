"""Benchmarks of uav_vs's hot paths (`make bench`)."""
