"""Detector-ready output of synthesized radar frames: View-of-Delft radar .bin files in the KITTI
layout that OpenPCDet's VoD configuration reads, optional uniform noise points (paper Table IV),
PCD files and preview images.

VoD layout (one folder per point-cloud kind, e.g. ``<root>/radar``)::

    radar/ImageSets/{train,val,test}.txt       one frame id per line
    radar/training/velodyne/NNNNN.bin          7 float32 per point (below); frames of the train and
                                               val splits here, of the test split under testing/
    radar/training/calib/NNNNN.txt             KITTI calib text (Tr_velo_to_cam = radar -> camera)
    radar/training/label_2/NNNNN.txt           KITTI labels (camera frame)
    radar/training/image_2/NNNNN.<ext>         the image (OpenPCDet reads the image size from it)

Radar .bin columns (float32 little-endian): x, y, z (m, radar frame {D}: x forward, y left, z up),
RCS (dataset RSS units), v_r (range rate m/s, negative approaching), v_r_compensated
(= v_r + u . v_ego, u the unit line of sight: the range rate the target would have if the radar
stood still), time (0 = current scan). Every file is written to a temporary name in the target
folder and renamed into place, so a killed run never leaves a half-written file.
"""

from __future__ import annotations

import os
import shutil
from collections import Counter
from collections.abc import Mapping, Sequence
from pathlib import Path

import cv2
import numpy as np
from pypcd4 import PointCloud

from pipeline.errors import ReaderError
from pipeline.fileio import atomic_path, write_atomic
from pipeline.frame import Object3D, check_shape, from_box_frame
from pipeline.geometry import spherical_to_cartesian, wrap_doppler
from pipeline.working import full_K

VOD_POINT_BYTES = 28
"""Bytes of a VoD radar .bin point: 7 float32, the columns of the module docstring."""
PCD_FIELDS = ("x", "y", "z", "rss", "doppler")
"""Fields of the PCD files, all float32."""


# --------------------------------------------------------------------------- VoD .bin


def vod_points(
    points_D: np.ndarray, rss: np.ndarray, doppler_rangerate: np.ndarray, ego_velocity_D: np.ndarray,
    doppler_span_mps: float = 0.0,
) -> np.ndarray:
    """(n, 7) float32 VoD rows from points (n, 3) m in {D}, RSS (n,), range rate (n,) m/s
    (positive receding; convert an Astyx-convention Doppler with its sign first) and the radar's
    ego velocity (3,) m/s in {D}. v_r_compensated = v_r + (u . v_ego), wrapped into the span of a
    radar that aliases (``doppler_span_mps`` > 0: its v_r is wrapped, so a static point would
    otherwise get a multiple of the span instead of 0); time = 0."""
    points = check_shape("points_D", np.asarray(points_D, dtype=np.float64), (None, 3))
    n = points.shape[0]
    rss = check_shape("rss", np.asarray(rss, dtype=np.float64), (n,))
    v_r = check_shape("doppler_rangerate", np.asarray(doppler_rangerate, dtype=np.float64), (n,))
    ego = check_shape("ego_velocity_D", np.asarray(ego_velocity_D, dtype=np.float64), (3,))
    norm = np.linalg.norm(points, axis=1, keepdims=True)
    unit = points / np.where(norm > 0, norm, 1.0)
    v_comp = wrap_doppler(v_r + unit @ ego, doppler_span_mps)
    return np.column_stack([points, rss, v_r, v_comp, np.zeros(n)]).astype(np.float32)


def radar_rows(points: np.ndarray, ego_velocity_D: np.ndarray, doppler_span_mps: float = 0.0) -> np.ndarray:
    """The VoD rows (n, 7) of a frame's synthesize ``points`` (n, 9; stages.synthesize): v_r from
    their range rate (column 8, positive receding), not their Doppler in the simulated radar's
    convention (column 6: Astyx's is positive approaching), which is the same only for a radar of
    Doppler sign +1; RSS column 7; the rest as :func:`vod_points`."""
    points = check_shape("points", np.asarray(points), (None, 9))
    return vod_points(points[:, :3], points[:, 7], points[:, 8], ego_velocity_D, doppler_span_mps)


def write_vod_rows(path: str | os.PathLike, rows: np.ndarray) -> Path:
    """Write ready (n, 7) VoD rows (e.g. with noise added) as little-endian float32, atomically."""
    rows = check_shape("rows", np.asarray(rows), (None, 7))
    return write_atomic(Path(path), rows.astype("<f4").tobytes())


def read_vod_bin(path: str | os.PathLike) -> np.ndarray:
    """Read a VoD radar .bin into (n, 7) float32; ReaderError if missing or not 28-byte rows."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise ReaderError(path, f"cannot read radar .bin: {exc.strerror or exc}") from exc
    if len(data) % VOD_POINT_BYTES:
        raise ReaderError(path, f"size {len(data)} bytes is not a multiple of {VOD_POINT_BYTES} (7 float32)")
    return np.frombuffer(data, dtype="<f4").reshape(-1, 7).astype(np.float32)


def add_uniform_noise(
    points: np.ndarray, fraction: float, rng: np.random.Generator, *,
    fov_az_deg: float, fov_el_deg: float, max_range_m: float,
    rss_range: tuple[float, float], doppler_range_mps: tuple[float, float],
    min_range_m: float = 0.5, ego_velocity_D: np.ndarray | None = None, doppler_span_mps: float = 0.0,
) -> np.ndarray:
    """Append round(fraction * n) uniform noise points to VoD rows (n, 7) (paper Table IV: 5%).

    Noise is uniform in range [min_range_m, max_range_m], azimuth and elevation within the TOTAL
    fields of view ``fov_*_deg`` (symmetric about x), RSS in ``rss_range`` and v_r (range rate) in
    ``doppler_range_mps``; v_r_compensated follows from ``ego_velocity_D`` (0 when None), wrapped
    into ``doppler_span_mps`` as in :func:`vod_points`; time 0.
    Returns (n + round(fraction * n), 7) float32, the input rows first.
    """
    rows = check_shape("points", np.asarray(points, dtype=np.float32), (None, 7))
    if not (np.isfinite(fraction) and fraction >= 0):
        raise ValueError(f"noise fraction must be >= 0, got {fraction}")
    if not 0 <= min_range_m < max_range_m:
        raise ValueError(f"noise range limits must satisfy 0 <= min < max, got {min_range_m}, {max_range_m}")
    k = int(round(fraction * rows.shape[0]))
    half_az, half_el = np.deg2rad(fov_az_deg) / 2, np.deg2rad(fov_el_deg) / 2
    rae = np.column_stack([
        rng.uniform(min_range_m, max_range_m, k),
        rng.uniform(-half_az, half_az, k),
        rng.uniform(-half_el, half_el, k),
    ])
    noise = vod_points(
        spherical_to_cartesian(rae), rng.uniform(*rss_range, k), rng.uniform(*doppler_range_mps, k),
        np.zeros(3) if ego_velocity_D is None else ego_velocity_D, doppler_span_mps,
    )
    return np.concatenate([rows, noise], axis=0)


# --------------------------------------------------------------------------- PCD


def write_pcd(path: str | os.PathLike, points_D: np.ndarray, rss: np.ndarray, doppler: np.ndarray) -> Path:
    """Write a binary PCD with float32 fields x y z rss doppler (points (n, 3) m in {D}), atomically."""
    points = check_shape("points_D", np.asarray(points_D, dtype=np.float32), (None, 3))
    n = points.shape[0]
    rss = check_shape("rss", np.asarray(rss, dtype=np.float32), (n,))
    doppler = check_shape("doppler", np.asarray(doppler, dtype=np.float32), (n,))
    cloud = PointCloud.from_points(
        np.column_stack([points, rss, doppler]), PCD_FIELDS, [np.float32] * len(PCD_FIELDS)
    )
    with atomic_path(path) as tmp, open(tmp, "wb") as handle:
        cloud.save(handle)
    return Path(path)


def read_pcd(path: str | os.PathLike) -> np.ndarray:
    """Read a PCD written by ``write_pcd`` into (n, 5) float32 [x, y, z, rss, doppler]."""
    path = Path(path)
    try:
        cloud = PointCloud.from_path(path)
    except (OSError, ValueError) as exc:
        raise ReaderError(path, f"cannot read PCD: {exc}") from exc
    missing = [f for f in PCD_FIELDS if f not in cloud.fields]
    if missing:
        raise ReaderError(path, f"PCD lacks fields {missing}")
    return np.asarray(cloud.numpy(PCD_FIELDS), dtype=np.float32).reshape(-1, len(PCD_FIELDS))


# --------------------------------------------------------------------------- preview


def preview_png(
    path: str | os.PathLike, image: np.ndarray, uv: np.ndarray, range_m: np.ndarray, max_range_m: float
) -> Path:
    """Write a PNG of ``image`` (H, W, 3) uint8 RGB with the points ``uv`` (n, 2) (pixels of that
    image, centres at integers) drawn as filled circles coloured by ``range_m`` (n,) on a fixed
    0 .. ``max_range_m`` scale (turbo colormap, near = blue), plus a colour bar with its limits.
    The output has the image's size."""
    image = check_shape("image", np.asarray(image), (None, None, 3))
    if image.dtype != np.uint8:
        raise ValueError(f"image: expected uint8, got {image.dtype}")
    uv = check_shape("uv", np.asarray(uv, dtype=np.float64), (None, 2))
    range_m = check_shape("range_m", np.asarray(range_m, dtype=np.float64), (uv.shape[0],))
    if not max_range_m > 0:
        raise ValueError(f"max_range_m must be > 0, got {max_range_m}")
    canvas = np.ascontiguousarray(cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
    h, w = canvas.shape[:2]
    level = np.clip(np.nan_to_num(range_m / max_range_m) * 255, 0, 255).astype(np.uint8)
    colours = (cv2.applyColorMap(level.reshape(-1, 1), cv2.COLORMAP_TURBO).reshape(-1, 3) if len(level)
               else np.zeros((0, 3), np.uint8))  # cv2 returns None for no points
    radius = max(2, round(min(w, h) / 160))
    finite = np.all(np.isfinite(uv), axis=1)
    for (u, v), colour in zip(np.rint(uv[finite]).astype(int), colours[finite]):
        cv2.circle(canvas, (int(u), int(v)), radius, tuple(int(c) for c in colour), -1, cv2.LINE_AA)
    _draw_colour_bar(canvas, max_range_m)
    return _write_png_bgr(path, canvas)


def _write_png_bgr(path: str | os.PathLike, canvas: np.ndarray) -> Path:
    """Encode an OpenCV (BGR) image as PNG and write it atomically."""
    ok, encoded = cv2.imencode(".png", canvas)
    if not ok:
        raise ValueError(f"{path}: PNG encoding failed")
    return write_atomic(Path(path), encoded.tobytes())


def _draw_colour_bar(canvas: np.ndarray, max_range_m: float) -> None:
    """Draw a horizontal range colour bar with '0 m' and 'max m' labels in the top-left corner."""
    h, w = canvas.shape[:2]
    bar_w, bar_h, x0, y0 = max(16, w // 4), max(4, h // 40), 4, 4
    if bar_w + 2 * x0 > w or bar_h + 2 * y0 > h:
        return
    ramp = np.linspace(0, 255, bar_w).astype(np.uint8).reshape(1, -1)
    bar = cv2.applyColorMap(np.repeat(ramp, bar_h, axis=0), cv2.COLORMAP_TURBO)
    canvas[y0:y0 + bar_h, x0:x0 + bar_w] = bar
    scale = max(0.3, min(w, h) / 800)
    ty = y0 + bar_h + int(14 * scale) + 2
    for text, x in (("0 m", x0), (f"{max_range_m:g} m", x0 + bar_w - int(40 * scale))):
        cv2.putText(canvas, text, (x, ty), cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0), 3, cv2.LINE_AA)
        cv2.putText(canvas, text, (x, ty), cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), 1, cv2.LINE_AA)


# --------------------------------------------------------------------------- KITTI / VoD layout


def _check_frame_id(frame_id: str) -> str:
    frame_id = str(frame_id)
    if not frame_id or "/" in frame_id or "\\" in frame_id or frame_id.startswith("."):
        raise ValueError(f"frame id {frame_id!r} is not a plain file stem")
    return frame_id


def _text_or_copy(dst: Path, source: str | os.PathLike) -> Path:
    """Write ``source`` to ``dst``: a str is the file's text, a Path / PathLike is copied."""
    if isinstance(source, str):
        return write_atomic(dst, source.encode())
    src = Path(source)
    if not src.is_file():
        raise ReaderError(src, "source file for the export does not exist")
    with atomic_path(dst) as tmp:
        shutil.copyfile(src, tmp)
    return dst


def write_kitti_layout(
    out_root: str | os.PathLike, frame_id: str, rows: np.ndarray, *,
    calib: str | os.PathLike | None = None, label: str | os.PathLike | None = None,
    image: os.PathLike | None = None, subset: str = "training",
) -> dict[str, Path]:
    """Write one frame into the VoD/KITTI layout under ``out_root`` (e.g. ``.../radar``).

    ``rows`` (n, 7) VoD rows -> ``<subset>/velodyne/<id>.bin``. ``calib`` / ``label``: a str is
    the file's text, a Path is a file to copy (-> ``calib/<id>.txt``, ``label_2/<id>.txt``);
    ``image``: a Path copied to ``image_2/<id><suffix>``. ``subset``: 'training' or 'testing'.
    Returns the written paths by kind ('velodyne', 'calib', 'label_2', 'image_2').
    """
    frame_id = _check_frame_id(frame_id)
    if subset not in ("training", "testing"):
        raise ValueError(f"subset must be 'training' or 'testing', got {subset!r}")
    base = Path(out_root) / subset
    written = {"velodyne": write_vod_rows(base / "velodyne" / f"{frame_id}.bin", rows)}
    if calib is not None:
        written["calib"] = _text_or_copy(base / "calib" / f"{frame_id}.txt", calib)
    if label is not None:
        written["label_2"] = _text_or_copy(base / "label_2" / f"{frame_id}.txt", label)
    if image is not None:
        if isinstance(image, str):
            raise ValueError("image must be a Path to copy, not text")
        written["image_2"] = _text_or_copy(base / "image_2" / f"{frame_id}{Path(image).suffix}", image)
    return written


DONT_CARE_LINE = "DontCare -1 -1 -10 0 0 0 0 -1 -1 -1 -1000 -1000 -1000 -10"
"""KITTI's placeholder label, written for a frame without objects: OpenPCDet's KITTI info generation
concatenates each file's boxes and fails on an empty file."""


def detector_label_text(text: str, track_ids: bool = False, P2: np.ndarray | None = None,
                        image_wh: tuple[int, int] | None = None) -> str:
    """KITTI label text for a detector. The second column is KITTI's truncation (0..1); View-of-Delft's
    tracking release and the synthetic world put track ids there, which OpenPCDet would read as
    truncation (boxes above 0.5 leave its evaluation and its ground-truth sampling). With
    ``track_ids`` (the reader knows the column holds them) it is replaced on every line, else where it
    lies outside 0..1: by the box's truncation when the camera's ``P2`` (3, 4) and the image size
    ``image_wh`` (W, H) are given (:func:`label_truncation`), else (or when a box field is no number)
    by 0. Fields are joined by single spaces (OpenPCDet splits on one space), blank lines dropped,
    lines with fewer than 15 fields kept as they are; a file without lines gets :data:`DONT_CARE_LINE`."""
    lines = []
    for line in text.splitlines():
        fields = line.split()
        if not fields:
            continue
        if len(fields) >= 15:
            try:
                truncation = float(fields[1])
            except ValueError:
                truncation = -1.0
            if track_ids or not 0.0 <= truncation <= 1.0:
                fields[1] = "0"
                if P2 is not None and image_wh is not None:
                    try:
                        fields[1] = f"{label_truncation(fields, P2, image_wh):.2f}"
                    except ValueError:  # a box field that is no number: 0, as without P2
                        pass
        lines.append(" ".join(fields))
    return "".join(f"{line}\n" for line in lines or [DONT_CARE_LINE])


def parse_class_map(text: str) -> dict[str, str]:
    """export.class_names ``'From=To,From2=To2'`` -> {'From': 'To', ...} ('' -> {}); ValueError
    saying what is wrong for an item without one '=', an empty or spaced name, or a name given twice.
    """
    mapping: dict[str, str] = {}
    for item in filter(None, (part.strip() for part in text.split(","))):
        names = [name.strip() for name in item.split("=")]
        if len(names) != 2 or not all(names) or any(" " in name for name in names):
            raise ValueError(f"'{item}' is not From=To (class names without spaces, e.g. Person=Pedestrian)")
        if names[0] in mapping:
            raise ValueError(f"'{names[0]}' is renamed twice")
        mapping[names[0]] = names[1]
    return mapping


def rename_classes(label_text: str, mapping: Mapping[str, str]) -> str:
    """KITTI label text with each line's class (its first field) renamed by ``mapping`` (classes not
    in it, DontCare included unless named, kept); other fields as they are."""
    if not mapping:
        return label_text
    lines = []
    for line in label_text.splitlines():
        name, sep, rest = line.partition(" ")
        lines.append(f"{mapping.get(name, name)}{sep}{rest}")
    return "".join(f"{line}\n" for line in lines)


def label_classes(label_text: str) -> Counter[str]:
    """Boxes per class of KITTI label text (DontCare left out)."""
    names = (line.split(" ", 1)[0] for line in label_text.splitlines())
    return Counter(name for name in names if name and name != "DontCare")


def calib_P2(calib: str | os.PathLike) -> np.ndarray:
    """The ``P2`` (3, 4) of a KITTI calib: its text (str) or its file (a path); ValueError naming the
    file when the line is missing or malformed."""
    text = calib if isinstance(calib, str) else Path(calib).read_text()
    for line in text.splitlines():
        key, _, values = line.partition(":")
        if key.strip() == "P2":
            try:
                return np.array(values.split(), np.float64).reshape(3, 4)
            except ValueError:
                break
    where = "calib text" if isinstance(calib, str) else str(calib)
    raise ValueError(f"{where}: no 'P2:' line with 12 numbers")


def label_truncation(fields: Sequence[str], P2: np.ndarray, image_wh: tuple[int, int]) -> float:
    """KITTI truncation of a label line's 3D box (``fields``: the line split on spaces; dimensions
    h w l in metres, location the bottom centre in the rectified camera frame, rotation_y) seen by
    the camera ``P2`` (3, 4) in an image ``image_wh`` (W, H): the share of its projected 2D box
    outside the image, as :func:`kitti_label_text` writes it; 1 when a corner is at or behind the
    camera plane or the box misses the image (nothing to measure the share on)."""
    P2 = check_shape("P2", np.asarray(P2, np.float64), (3, 4))
    h, w, length, x, y, z, ry = (float(v) for v in fields[8:15])
    dx, dy, dz = np.meshgrid([-length / 2, length / 2], [-h, 0.0], [-w / 2, w / 2], indexing="ij")
    c, s = np.cos(ry), np.sin(ry)
    corners_cam = np.stack([c * dx.ravel() + s * dz.ravel() + x, dy.ravel() + y,
                            -s * dx.ravel() + c * dz.ravel() + z], axis=1)
    if np.any(corners_cam[:, 2] <= NEAR_PLANE_M):
        return 1.0
    uvw = corners_cam @ P2[:, :3].T + P2[:, 3]
    box = _clipped_box(uvw[:, :2] / uvw[:, 2:3], image_wh)
    return 1.0 if box is None else box[1]


def _clipped_box(uv: np.ndarray, image_wh: tuple[int, int]) -> tuple[tuple[float, ...], float] | None:
    """The 2D box (u0, v0, u1, v1) of projected corners ``uv`` (N, 2) px clipped to an image
    ``image_wh`` (W, H), and the share of the unclipped box outside it; None when it misses the image."""
    (u0, v0), (u1, v1) = uv.min(axis=0), uv.max(axis=0)
    cu0, cv0, cu1, cv1 = max(u0, 0.0), max(v0, 0.0), min(u1, image_wh[0] - 1.0), min(v1, image_wh[1] - 1.0)
    if cu1 <= cu0 or cv1 <= cv0:
        return None
    return (cu0, cv0, cu1, cv1), 1.0 - (cu1 - cu0) * (cv1 - cv0) / max((u1 - u0) * (v1 - v0), 1e-9)


NEAR_PLANE_M = 0.1
"""Camera depth (m) at or below which a box corner counts as at or behind the camera."""

_BOX_EDGES = np.array([(a, a ^ bit) for a in range(8) for bit in (1, 2, 4) if a < a ^ bit])
"""The 12 edges (12, 2) of a box's 8 corners in meshgrid 'ij' order: the pairs differing in one coordinate."""


def in_front_of_camera(corners_cam: np.ndarray) -> np.ndarray:
    """The vertices (N, 3) of the part of a box in front of the camera plane z = NEAR_PLANE_M: its
    corners there and the points where its edges cross the plane. ``corners_cam`` (8, 3) m in the
    camera frame, in meshgrid 'ij' order of the box axes' signs. (0, 3) for a box wholly behind."""
    corners = check_shape("corners_cam", np.asarray(corners_cam, np.float64), (8, 3))
    front = corners[:, 2] > NEAR_PLANE_M
    a, b = corners[_BOX_EDGES[:, 0]], corners[_BOX_EDGES[:, 1]]
    cross = front[_BOX_EDGES[:, 0]] != front[_BOX_EDGES[:, 1]]
    t = (NEAR_PLANE_M - a[cross, 2]) / (b[cross, 2] - a[cross, 2])
    return np.concatenate([corners[front], a[cross] + t[:, None] * (b[cross] - a[cross])])


def kitti_label_text(objects: Sequence[Object3D], T_cam_radar: np.ndarray, K: np.ndarray,
                     image_wh: tuple[int, int]) -> str:
    """KITTI label lines of boxes in {D} for a calib whose rectified camera is the camera of
    ``T_cam_radar`` (4, 4) and ``K`` (3, 3), R0_rect identity (:func:`kitti_calib_text`), written so
    that OpenPCDet's reading gives the boxes back: ``location`` the bottom centre (the box centre
    lowered by h/2 along {D}'s z) in the camera frame, rotation_y = -(yaw + pi/2) (its
    ``boxes3d_kitti_camera_to_lidar``). OpenPCDet's boxes are upright in the point cloud's frame,
    here {D}: a tilted box (Astyx) is written as the upright box with its centre, size and heading,
    the yaw being the heading of its length axis projected on {D}'s x-y plane (Object3D's
    convention), not measured in the camera's x-z plane (on Astyx, whose camera is turned 1 deg
    against the radar, that differs by 0.9-1.2 deg and OpenPCDet would read every box turned by
    it). alpha = rotation_y - atan2(x, z); the 2D box is the projection of the 8 corners of the box
    with its full rotation (``Object3D.rotation``) clipped to the image ``image_wh`` (W, H),
    truncation the share of it outside the image; occlusion 0 (not known). A box reaching behind the
    camera plane (an object beside the car) gets the 2D box of its part in front
    (:func:`in_front_of_camera`) and truncation 1, as :func:`label_truncation` gives such a box;
    boxes wholly behind it or wholly outside the image are left out (KITTI labels what the camera
    sees); spaces in class names become '_'. A frame without boxes gets :data:`DONT_CARE_LINE`."""
    T = check_shape("T_cam_radar", np.asarray(T_cam_radar, np.float64), (4, 4))
    K = check_shape("K", np.asarray(K, np.float64), (3, 3))
    lines = []
    for obj in objects:
        length, width, height = (float(v) for v in obj.size_lwh_m)
        local = np.stack([v.ravel() for v in np.meshgrid([-length / 2, length / 2], [-width / 2, width / 2],
                                                         [-height / 2, height / 2], indexing="ij")], axis=1)
        corners_D = np.asarray(obj.center_D, np.float64) + from_box_frame(local, obj.rotation)
        corners_cam = corners_D @ T[:3, :3].T + T[:3, 3]
        reaches_behind = bool(np.any(corners_cam[:, 2] <= NEAR_PLANE_M))
        seen = in_front_of_camera(corners_cam) if reaches_behind else corners_cam
        box = _clipped_box((seen @ K.T)[:, :2] / seen[:, 2:3], image_wh) if len(seen) else None
        if box is None:
            continue
        (cu0, cv0, cu1, cv1), truncation = box[0], 1.0 if reaches_behind else box[1]
        bottom_cam = T[:3, :3] @ (np.asarray(obj.center_D, np.float64) - [0.0, 0.0, height / 2]) + T[:3, 3]
        ry = float(np.angle(np.exp(-1j * (obj.yaw_rad + np.pi / 2))))
        alpha = float(np.angle(np.exp(1j * (ry - np.arctan2(bottom_cam[0], bottom_cam[2])))))
        values = [truncation, 0, alpha, cu0, cv0, cu1, cv1, height, width, length, *bottom_cam, ry]
        lines.append(" ".join([obj.class_name.replace(" ", "_"), *(f"{v:.6g}" for v in values)]))
    return "".join(f"{line}\n" for line in lines or [DONT_CARE_LINE])


IMAGE_FORMATS = {"source": None, "png": ".png", "jpg": ".jpg"}
"""The suffix each value of export.image_format (pipeline.config.CHOICES) writes (source: the
dataset's own file as it is, the reader's image as PNG where there is none)."""


def write_image(path: str | os.PathLike, image: np.ndarray) -> Path:
    """Write ``image`` (H, W, 3) uint8 RGB at ``path`` (atomically), PNG or JPEG (quality 95) by the
    path's suffix."""
    image = check_shape("image", np.asarray(image), (None, None, 3))
    if image.dtype != np.uint8:
        raise ValueError(f"image: expected uint8, got {image.dtype}")
    suffix = Path(path).suffix.lower()
    if suffix not in (".png", ".jpg", ".jpeg"):
        raise ValueError(f"{path}: images are written as .png or .jpg")
    params = [cv2.IMWRITE_JPEG_QUALITY, 95] if suffix != ".png" else []
    ok, encoded = cv2.imencode(suffix, np.ascontiguousarray(image[:, :, ::-1]), params)
    if not ok:
        raise ValueError(f"{path}: image encoding failed")
    return write_atomic(Path(path), encoded.tobytes())


CALIB_KEYS = ("P0", "P1", "P2", "P3", "R0_rect", "Tr_velo_to_cam", "Tr_imu_to_velo")
"""KITTI calib keys in the order of KITTI's files: OpenPCDet's KITTI-style readers take P2, P3,
R0_rect and Tr_velo_to_cam from lines 3 to 6 by position, not by key."""
CALIB_SHAPES = {"P0": (3, 4), "P1": (3, 4), "P2": (3, 4), "P3": (3, 4), "R0_rect": (3, 3),
                "Tr_velo_to_cam": (3, 4), "Tr_imu_to_velo": (3, 4)}


def calib_text(matrices: Mapping[str, np.ndarray]) -> str:
    """KITTI calib text of ``matrices`` ({key: matrix} for every key of :data:`CALIB_KEYS`, shapes
    :data:`CALIB_SHAPES`), one ``key: values`` line each in KITTI's order."""
    missing = [key for key in CALIB_KEYS if key not in matrices]
    if missing:
        raise ValueError(f"calib: missing {', '.join(missing)}")
    lines = []
    for key in CALIB_KEYS:
        values = check_shape(key, np.asarray(matrices[key], dtype=np.float64), CALIB_SHAPES[key])
        if not np.all(np.isfinite(values)):
            raise ValueError(f"calib: {key} has non-finite values")
        lines.append(key + ": " + " ".join(f"{v:.12e}" for v in values.ravel()))
    return "\n".join(lines) + "\n"


def kitti_calib_text(P2: np.ndarray, T_cam_radar: np.ndarray) -> str:
    """KITTI calib text for a frame without a calib file (VoD radar convention: ``Tr_velo_to_cam``
    maps radar {D} to the rectified camera). ``P2`` (3, 4) projection of the exported image;
    P0..P3 all set to P2, R0_rect identity, Tr_imu_to_velo identity."""
    P2 = check_shape("P2", np.asarray(P2, dtype=np.float64), (3, 4))
    T = check_shape("T_cam_radar", np.asarray(T_cam_radar, dtype=np.float64), (4, 4))
    return calib_text({**{f"P{i}": P2 for i in range(4)}, "R0_rect": np.eye(3), "Tr_velo_to_cam": T[:3],
                       "Tr_imu_to_velo": np.eye(4)[:3]})


def generated_calib(K_working: np.ndarray, T_cam_radar: np.ndarray, crop_rows: Sequence[int],
                    full_wh: Sequence[int], working_wh: Sequence[int]) -> str:
    """KITTI calib text for a dataset without calib files (Astyx): P2 the camera at the reader's full
    resolution ``full_wh`` (the images exported beside it), not the cropped (``crop_rows``), resized
    (``working_wh``) camera ``K_working`` the stages use; Tr_velo_to_cam ``T_cam_radar`` ({D} to
    camera)."""
    K_full = full_K(K_working, crop_rows, full_wh, working_wh)
    return kitti_calib_text(np.column_stack([K_full, np.zeros(3)]), T_cam_radar)


def write_image_sets(out_root: str | os.PathLike, split: Mapping[str, Sequence[str]]) -> dict[str, Path]:
    """Write ``ImageSets/<name>.txt`` (one frame id per line, in the given order) under ``out_root``
    for each split name (train, val, test, ...); returns the paths by name."""
    written = {}
    for name, ids in split.items():
        if not name or "/" in name:
            raise ValueError(f"split name {name!r} is not a plain file stem")
        text = "".join(f"{_check_frame_id(i)}\n" for i in ids)
        written[name] = write_atomic(Path(out_root) / "ImageSets" / f"{name}.txt", text.encode())
    return written
