"""Built-in synthetic driving world with a hidden radar model, written in the View-of-Delft layout.

``generate(out_dir, frames, seed, ...)`` writes camera images, lidar scans, radar points, labels,
calibration, poses and a ``world.json`` summary (written last). See generator.py.
"""

from pipeline.world.generator import generate

__all__ = ["generate"]
