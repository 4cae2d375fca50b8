"""Stereo(-inertial) ORB visual odometry front-end of the agent."""
