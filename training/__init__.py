"""Offline training: MCAP bags -> Stage I trajectory teacher -> Stage II video students -> ONNX.

Run as `python -m training <command> --help` (`python -m training --help` lists the commands), with
ros_ws/src/ad_sim and ros_ws/src/ad_estimator importable (sourced workspace or PYTHONPATH).
"""
