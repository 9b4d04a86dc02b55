"""Analytic Dynamics estimator: onnxruntime material estimation (never imports torch) and thin ROS 2 executables."""
