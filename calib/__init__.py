"""Hand-eye calibration of the stationary laser profilers against the robot base."""
