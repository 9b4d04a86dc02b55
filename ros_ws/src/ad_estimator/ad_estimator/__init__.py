"""Analytic Dynamics estimator: onnxruntime material estimation (never imports torch) and thin ROS 2 executables.

Without ROS, in your own process: images.array_to_mask, parameters.model_window and model.EstimatorModel
(docs/estimator.md, "In your own Python process, without ROS", has an example that runs)."""
