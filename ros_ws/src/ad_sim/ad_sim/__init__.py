"""Analytic Dynamics simulator: Warp MPM library (importable without ROS) and thin ROS 2 executables."""
