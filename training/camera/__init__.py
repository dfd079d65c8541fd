"""Camera detector training: torch net, data, loss, training loop, ONNX export, int8 quantization."""
