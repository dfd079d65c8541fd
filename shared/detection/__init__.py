"""Detectors behind one interface (shared/detection/interface.py): learned ONNX camera and lidar
models, a classical clustering lidar detector and a noisy-ground-truth oracle."""
