"""uav_vs.flight: missions (chapter section 5 tasks), flight recording, replay, report, plots."""
