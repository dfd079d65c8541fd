"""Lidar detectors: a learned PointPillars model (pointpillars/) and classical clustering."""
