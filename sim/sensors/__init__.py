"""Simulated sensors: commanded velocity with wheel slip, IMU, stereo rock detector, orbital catalog."""
