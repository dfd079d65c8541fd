"""Camera (2D) detector: a small anchor-free single-stage CNN, trained from scratch, run on onnxruntime.

    config.py         CameraDetectorConfig: input size, network, augmentation, training, thresholds
    geometry.py       letterbox, NMS, post-processing to original pixels (numpy + OpenCV)
    onnx_detector.py  OnnxCameraDetector (the CameraDetector protocol) and measure_latency: no torch

Training (torch net, data, loss, `python -m training.camera.train`), ONNX export and int8 quantization
live in `training/camera/`; run time needs none of them.
"""
