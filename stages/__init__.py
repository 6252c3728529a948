"""The pipeline's stages, in execution order. Each module declares one stage (``STAGE``); evaluate
also its per-frame part (``FRAMES``, evaluate-frames)."""

from __future__ import annotations


def all_stages() -> list:
    """Every stage declaration, upstream first."""
    from stages import calibrate, evaluate, export, heatmaps, patches, synthesize, train

    return [calibrate.STAGE, heatmaps.STAGE, patches.STAGE, train.STAGE, synthesize.STAGE, export.STAGE,
            evaluate.FRAMES, evaluate.STAGE]
