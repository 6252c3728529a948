"""Simulate a commercial automotive 4D radar from camera + lidar inputs (Song et al., IROS 2025)."""

__version__ = "0.1.0"
