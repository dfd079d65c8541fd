"""Training tools, apart from runtime inference: the torch models, their data, losses and training
loops, ONNX export and int8 quantization (`python -m training.camera.train`, `make models`). Runtime
inference (`shared/detection/`) loads only the exported ONNX models and never imports torch."""
