"""PointPillars training: torch net, data, training loop and accuracy, ONNX export, int8 quantization."""
