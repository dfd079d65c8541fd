"""Camera (2D) detector: a small anchor-free single-stage CNN, trained from scratch, run on onnxruntime.

    config.py         CameraDetectorConfig: input size, network, augmentation, training, thresholds
    geometry.py       letterbox, NMS, post-processing to original pixels (numpy + OpenCV)
    onnx_detector.py  OnnxCameraDetector (the CameraDetector protocol) and measure_latency: no torch
    net.py            the network and its box decoding (torch)
    data.py           Dataset over the generated layout, augmentation, target assignment (torch)
    loss.py           quality focal loss + GIoU loss (torch)
    train.py          `python -m shared.detection.camera.train --data ROOT --out DIR`
    export.py         ONNX export + onnx.checker + onnxruntime-vs-torch check

Run time imports only config, geometry and onnx_detector; torch is needed for training and export.
"""
