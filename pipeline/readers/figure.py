"""README figures: lidar and radar points projected onto the camera image through the readers.

``python -m pipeline.readers.figure --data ../shared/data --out docs`` writes
``overlay_astyx.png`` (one frame of each Astyx calibration set: < 470 and >= 470) and
``overlay_vod.png`` (the two View-of-Delft example frames). Lidar is drawn small and coloured by
camera depth, radar as larger dots coloured by range rate (m/s, red receding, blue approaching).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from pipeline.config import load_config
from pipeline.frame import FrameRecord
from pipeline.geometry import invert_transform, project_to_image
from pipeline.readers import get_reader


def draw_overlay(ax, record: FrameRecord, title: str, max_lidar: int = 20000) -> None:
    """Draw ``record``'s image with its lidar and radar points projected (matplotlib axes ``ax``)."""
    h, w = record.image.shape[:2]
    T_cam_radar = invert_transform(record.T_radar_cam)
    ax.imshow(record.image)
    uv, depth, valid = project_to_image(record.lidar_D, record.K, T_cam_radar, (w, h))
    idx = np.flatnonzero(valid)
    if idx.size > max_lidar:
        idx = np.random.default_rng(0).choice(idx, max_lidar, replace=False)
    ax.scatter(uv[idx, 0], uv[idx, 1], c=depth[idx], s=0.3 if idx.size > 5000 else 2.5, cmap="viridis", vmin=0, vmax=50, linewidths=0)
    uv_r, _, valid_r = project_to_image(record.radar_D[:, :3], record.K, T_cam_radar, (w, h))
    sc = ax.scatter(uv_r[valid_r, 0], uv_r[valid_r, 1], c=record.radar_D[valid_r, 3], s=9, cmap="coolwarm",
                    vmin=-5, vmax=5, edgecolors="k", linewidths=0.3)
    ax.set_xlim(-0.5, w - 0.5)
    ax.set_ylim(h - 0.5, -0.5)
    ax.set_title(f"{title}: {valid_r.sum()} radar / {valid.sum()} lidar points in view, "
                 f"|v_ego| {np.linalg.norm(record.ego_velocity_D):.2f} m/s", fontsize=8)
    ax.axis("off")
    return sc


def write_figure(records: list[tuple[FrameRecord, str]], out_path: Path, width_in: float) -> None:
    """Stack the overlays of ``records`` vertically into ``out_path`` (PNG, Agg backend)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    h, w = records[0][0].image.shape[:2]
    fig, axes = plt.subplots(len(records), 1, figsize=(width_in, width_in * h / w * len(records) + 0.6))
    for ax, (record, title) in zip(np.atleast_1d(axes), records):
        sc = draw_overlay(ax, record, title)
    fig.colorbar(sc, ax=np.atleast_1d(axes).tolist(), fraction=0.02, pad=0.01, label="radar range rate (m/s)")
    out_path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out_path, dpi=110, bbox_inches="tight")
    plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    """Write overlay_astyx.png and overlay_vod.png from the real data folder."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, required=True, help="folder holding astyx_hires2019/ and vod_example/")
    parser.add_argument("--out", type=Path, default=Path("docs"))
    args = parser.parse_args(argv)
    astyx = get_reader(load_config("astyx"), args.data / "astyx_hires2019" / "dataset_astyx_hires2019")
    write_figure([(astyx.read("000000"), "Astyx 000000 (calibration set frames 0-469)"),
                  (astyx.read("000480"), "Astyx 000480 (calibration set frames 470-545)")],
                 args.out / "overlay_astyx.png", width_in=10)
    vod = get_reader(load_config("vod"), args.data / "vod_example")
    write_figure([(vod.read(f), f"View-of-Delft {f}") for f in vod.frame_ids()], args.out / "overlay_vod.png",
                 width_in=7)


if __name__ == "__main__":
    main()
