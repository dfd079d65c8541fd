"""Experiments on the simulated table (`make experiments`): the paper's traffic-flow experiment."""
