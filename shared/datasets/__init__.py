"""Dataset formats (YOLO, Pascal VOC, KITTI object, OpenPCDet custom) and the layout of the datasets
`rmmdet dataset generate` writes (layout.py)."""
