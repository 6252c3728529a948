"""README figure of the synthetic world: image, lidar projected (by depth), radar projected (by Doppler).

Usage: ``python -m pipeline.world.figure OUT.png [--seed N]``. Generates a small world (one short
sequence per scene type) into a temporary folder and reads the written VoD files back, so the
figure also shows that the files are consistent (calibration, projections, Doppler sign).
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np


def read_calib(path: Path) -> dict[str, np.ndarray]:
    """KITTI calibration text -> {key: values}; keys without numbers map to empty arrays."""
    out = {}
    for line in path.read_text().splitlines():
        if ":" in line:
            key, vals = line.split(":", 1)
            out[key.strip()] = np.array([float(v) for v in vals.split()], np.float64)
    return out


def project(points: np.ndarray, calib: dict[str, np.ndarray], size_wh: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Project sensor points (N, 3) with P2 @ Tr_velo_to_cam; returns pixels (M, 2) and the kept indices (M,)."""
    T = np.eye(4)
    T[:3, :4] = calib["Tr_velo_to_cam"].reshape(3, 4)
    P = calib["P2"].reshape(3, 4)
    cam = points @ T[:3, :3].T + T[:3, 3]
    front = np.flatnonzero(cam[:, 2] > 0.5)
    uvw = cam[front] @ P[:, :3].T + P[:, 3]
    uv = uvw[:, :2] / uvw[:, 2:3]
    w, h = size_wh
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
    return uv[inside], front[inside]


def make_figure(out_png: Path, seed: int = 0) -> None:
    """Generate a small world and draw three frames (one per scene type) into ``out_png``."""
    import cv2
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from pipeline.world.generator import generate

    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        generate(root, frames=12, seed=seed, resolution_wh=(640, 384), sequence_len=4)
        fig, axes = plt.subplots(3, 3, figsize=(13.6, 6.9))
        fig.subplots_adjust(wspace=0.02, hspace=0.06)
        for row, frame in enumerate(("00002", "00006", "00010")):
            img = cv2.imread(str(root / "lidar/training/image_2" / f"{frame}.png"))[..., ::-1]
            h, w = img.shape[:2]
            lidar = np.fromfile(root / "lidar/training/velodyne" / f"{frame}.bin", np.float32).reshape(-1, 4)
            radar = np.fromfile(root / "radar/training/velodyne" / f"{frame}.bin", np.float32).reshape(-1, 7)
            uv_l, i_l = project(lidar[:, :3].astype(np.float64), read_calib(root / "lidar/training/calib" / f"{frame}.txt"), (w, h))
            uv_r, i_r = project(radar[:, :3].astype(np.float64), read_calib(root / "radar/training/calib" / f"{frame}.txt"), (w, h))
            depth = np.linalg.norm(lidar[i_l, :3], axis=1)
            ax = axes[row]
            ax[0].imshow(img)
            ax[1].imshow(img)
            sc = ax[1].scatter(uv_l[:, 0], uv_l[:, 1], c=depth, s=0.4, cmap="turbo", vmin=0, vmax=60)
            ax[2].imshow(img)
            sr = ax[2].scatter(uv_r[:, 0], uv_r[:, 1], c=radar[i_r, 4], s=9, cmap="coolwarm", vmin=-15, vmax=15,
                               edgecolors="k", linewidths=0.3)
            ax[0].set_ylabel(f"frame {frame}")
            for a in ax:
                a.set_xticks([])
                a.set_yticks([])
        axes[0, 0].set_title("camera (synthetic)")
        axes[0, 1].set_title("lidar projected, colour = range (m)")
        axes[0, 2].set_title("radar projected, colour = Doppler v_r (m/s)")
        fig.colorbar(sc, ax=axes[:, 1], fraction=0.02, pad=0.01)
        fig.colorbar(sr, ax=axes[:, 2], fraction=0.02, pad=0.01)
        out_png.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(out_png, dpi=100, bbox_inches="tight")
        plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out_png", type=Path)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    make_figure(args.out_png, args.seed)


if __name__ == "__main__":
    main()
