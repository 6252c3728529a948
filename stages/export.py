"""export: synthesized radar in detector-ready layouts.

Reads: synthesize (points), calibrate (image, K, T_radar_cam, ego_velocity, ego_velocity_known,
split), and the raw
dataset's calib, label and image files that its reader names (Reader.detector_files: VoD and the
synthetic world their own files; KITTI its calib with the radar in the Velodyne's place, and its
labels), else the reader's image and (Astyx) its annotated objects.
Writes (export/): radar/<subset>/velodyne/<id>.bin (7 float32: x, y, z, RCS, v_r,
v_r_compensated, time = 0, the View-of-Delft radar layout that OpenPCDet's VoD configuration
reads), with <subset> 'training' for frames of the train and val splits and 'testing' for the
test split (where OpenPCDet looks for them); <subset>/calib/<id>.txt carried over, or generated
from the full-resolution K and T_radar_cam when the dataset has none; <subset>/label_2/<id>.txt
carried over with track ids replaced by each box's truncation (pipeline.export.detector_label_text),
or written from the reader's objects for the generated calib (pipeline.export.kitti_label_text);
<subset>/image_2/<id> (export.images, in export.image_format); radar/ImageSets/{train,val,test}.txt;
optional
pcd/<id>.pcd and preview/<id>.png (image with the points coloured by range);
ego_velocity_unknown.txt, the frames whose dataset records no ego motion (their Doppler is a
stopped car's: filter them out of Doppler-using training), absent when there are none;
object_velocity_unknown.txt, the frames with points on labelled objects whose velocity the dataset
does not record (no track to difference: the View-of-Delft example frames, Astyx), whose Doppler is
a static object's, absent when there are none; label_missing.txt, the frames under training/
written without a label_2 file (the dataset labels none for them; OpenPCDet's info generation
needs one for every train and val frame), absent when there are none.
Config: export.* (noise_fraction: the paper's 5% uniform noise points; class_names: classes renamed
in the labels, whose boxes per class the summary counts), radar.* (noise bounds, the
Doppler span that v_r and v_r_compensated lie in),
camera.* (the full-resolution K of a generated calib).
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pipeline.cache import DONE
from pipeline.config import Config
from pipeline.errors import ConfigError, PipelineError
from pipeline.geometry import invert_transform, project_to_image
from pipeline.progress import bar as progress_bar
from pipeline.stage import DatasetStage

CONFIG_KEYS = ("export.noise_fraction", "export.pcd", "export.previews", "export.images", "export.image_format",
               "export.class_names",
               "radar.fov_az_deg",
               "radar.fov_el_deg", "radar.max_range_m", "radar.rss_min", "radar.rss_max", "radar.doppler_sign",
               "radar.doppler_span_mps",
               "camera.full_size", "camera.crop_rows", "camera.working_size")
VERSION = 9
"""2: test-split frames under testing/, image_2, full-resolution generated calib, truncation column.
3: KITTI's own calib (the radar in the Velodyne's place), labels and images carried over; track ids
out of the truncation column wherever the reader knows them; DontCare for a frame without labels;
export.image_format; Astyx's annotations as KITTI labels (pipeline.export.kitti_label_text);
v_r_compensated wrapped into an aliasing radar's span (Astyx: 56% of its points had +-10.4 m/s).
4: a track id's truncation column gets the box's truncation from the calib's P2, not 0 (boxes cut by
the image edge were rated 'Easy' by OpenPCDet).
5: export.class_names renames classes in the labels; the summary counts the boxes per class.
6: object_velocity_unknown.txt and the summary's count of points on objects of unknown velocity.
7: label_missing.txt and the summary's count of training/ frames without a label file.
8: Astyx's labels: the 2D box and truncation from the projected corners of the tilted box (the
reader keeps its pitch and roll); location and rotation_y as before.
9: labels written from {D} (Astyx): a box reaching behind the camera plane (an object beside the car)
is written with the 2D box of its part in front and truncation 1, not left out."""
SPLIT_NAMES = {0: "train", 1: "val", 2: "test"}


@dataclass
class _Tally:
    """What the export has written so far: the image sets and the summary's counts."""

    lists: dict[str, list[str]] = field(default_factory=lambda: {name: [] for name in SPLIT_NAMES.values()})
    no_motion: list[str] = field(default_factory=list)  # frames whose dataset records no ego motion
    empty: list[str] = field(default_factory=list)      # frames written without a point
    unlabelled: list[str] = field(default_factory=list)  # frames under training/ written without label_2
    unknown_motion: dict[str, int] = field(default_factory=dict)  # frame -> points on objects of unknown velocity
    classes: dict[str, Counter[str]] = field(default_factory=lambda: {"training": Counter(), "testing": Counter()})
    unused: set[str] = field(default_factory=set)  # names of export.class_names no label holds (a misspelt class)
    points: int = 0
    noise: int = 0


def run(inputs, cfg: Config, out, fingerprint: str) -> dict:
    from pipeline.export import parse_class_map, write_image_sets

    syn, calib = inputs.store("synthesize"), inputs.store("calibrate")
    done = np.flatnonzero(syn.status() == DONE)
    if len(done) == 0:
        raise PipelineError(f"export: synthesize has no finished frame (synth.split = '{cfg.synth.split}')")
    split = np.asarray(calib.array("split")[:])
    root = Path(out.path)
    class_map = parse_class_map(cfg.export.class_names)  # checked by check()
    tally = _Tally(unused=set(class_map))
    for i in progress_bar(done, total=len(done), desc="export", unit="frame", enabled=inputs.progress,
                          every_s=cfg.run.progress_every_s):
        i = int(i)
        export_frame(inputs.frame(i), inputs.frame_ids[i], syn.read("points", i),
                     SPLIT_NAMES.get(int(split[i]), "test"), cfg, root, class_map, tally)
    write_image_sets(root / "radar", tally.lists)
    if tally.no_motion:
        (root / NO_MOTION_LIST).write_text("\n".join(tally.no_motion) + "\n")
    if tally.unknown_motion:
        (root / UNKNOWN_OBJECT_MOTION_LIST).write_text("\n".join(tally.unknown_motion) + "\n")
    if tally.unlabelled:
        (root / UNLABELLED_LIST).write_text("\n".join(tally.unlabelled) + "\n")
    n_unknown = sum(tally.unknown_motion.values())
    return {"frames": int(len(done)), "points": int(tally.points), "noise_points": int(tally.noise),
            "output": str(root), "no_ego_motion": len(tally.no_motion), "empty_frames": tally.empty,
            "object_motion_unknown": {"frames": len(tally.unknown_motion), "points": int(n_unknown)},
            "training_frames_without_label": len(tally.unlabelled),
            "classes": {subset: dict(counts) for subset, counts in tally.classes.items()},
            "classes_not_found": sorted(tally.unused), "message": _message(tally, len(done), root, cfg)}


def export_frame(f, fid: str, pts: np.ndarray, split_name: str, cfg: Config, root: Path,
                 class_map: dict[str, str], tally: _Tally) -> None:
    """Write one frame's files under ``root`` (its synthesized ``pts`` (N, 9) in synthesize's
    columns, its calib, label, image, and the optional PCD and preview) and add it to ``tally``.
    ``f``: the frame's inputs (FrameInputs); ``split_name``: 'train', 'val' or 'test'."""
    from pipeline.export import label_classes, preview_png, rename_classes, write_kitti_layout, write_pcd
    from pipeline.synthesis import on_objects_of_unknown_velocity

    rows, n_noise = _radar_rows(f, pts, cfg)
    K, T_cam_radar = f.get("calibrate", "K"), invert_transform(f.get("calibrate", "T_radar_cam"))
    subset = "testing" if split_name == "test" else "training"
    calib_src, label, image_src, record = _detector_files(f, fid, K, T_cam_radar, cfg)
    if label is not None:
        tally.unused -= set(label_classes(label))
        label = rename_classes(label, class_map)
        tally.classes[subset].update(label_classes(label))  # as written: two classes renamed to one add up
    elif subset == "training":
        tally.unlabelled.append(fid)
    radar_root = root / "radar"
    write_kitti_layout(radar_root, fid, rows, calib=calib_src, image=image_src, subset=subset, label=label)
    if len(rows) == 0:
        tally.empty.append(fid)
    if cfg.export.images and image_src is None:  # the reader's image, in the chosen format
        from pipeline.export import IMAGE_FORMATS, write_image

        suffix = IMAGE_FORMATS[cfg.export.image_format]
        write_image(radar_root / subset / "image_2" / f"{fid}{suffix or '.png'}", record.image)
    if cfg.export.pcd:
        write_pcd(root / "pcd" / f"{fid}.pcd", pts[:, :3], pts[:, 7], pts[:, 6])
    if cfg.export.previews:
        image = f.get("calibrate", "image")
        uv, _, valid = project_to_image(pts[:, :3], K, T_cam_radar, (image.shape[1], image.shape[0]))
        preview_png(root / "preview" / f"{fid}.png", image, uv[valid], pts[valid, 3], cfg.radar.max_range_m)
    tally.lists[split_name].append(fid)
    if not f.get("calibrate", "ego_velocity_known"):
        tally.no_motion.append(fid)
    on_unknown = int(on_objects_of_unknown_velocity(pts[:, :3], f.get("calibrate", "labels")).sum())
    if on_unknown:
        tally.unknown_motion[fid] = on_unknown
    tally.points += len(pts)
    tally.noise += n_noise


def _radar_rows(f, pts: np.ndarray, cfg: Config) -> tuple[np.ndarray, int]:
    """The frame's VoD radar rows (pipeline.export.radar_rows) with export.noise_fraction of uniform
    noise points added, and how many were added."""
    from pipeline.export import add_uniform_noise, radar_rows

    ego, span, r = f.get("calibrate", "ego_velocity"), cfg.radar.doppler_span_mps, cfg.radar
    rows = radar_rows(pts, ego, span)
    if cfg.export.noise_fraction <= 0:
        return rows, 0
    noisy = add_uniform_noise(rows, cfg.export.noise_fraction, f.rng(cfg.synth.seed, 31),
                              fov_az_deg=r.fov_az_deg, fov_el_deg=r.fov_el_deg, max_range_m=r.max_range_m,
                              rss_range=(r.rss_min, r.rss_max),
                              doppler_range_mps=(-span / 2, span / 2) if span > 0 else (-15.0, 15.0),
                              ego_velocity_D=ego, doppler_span_mps=span)
    return noisy, len(noisy) - len(rows)


def _detector_files(f, fid: str, K: np.ndarray, T_cam_radar: np.ndarray, cfg: Config) -> tuple:
    """(calib, label, image, record) of a frame for the detector layout: the dataset's calib (text,
    or a path to carry over) or one generated from the working ``K`` and ``T_cam_radar``; its label
    text (track ids replaced by truncation) or one written from the reader's objects for a generated
    calib, else None; the dataset's image file to carry over where export.image_format keeps its
    format, else None; the reader's record where the label or the image must come from it, else None."""
    from pipeline.export import (IMAGE_FORMATS, calib_P2, calib_text, detector_label_text, generated_calib,
                                 kitti_label_text)
    from pipeline.working import full_K

    c, src = cfg.camera, f.reader.detector_files(fid)
    calib_src = calib_text(src.calib) if isinstance(src.calib, dict) else src.calib
    suffix = IMAGE_FORMATS[cfg.export.image_format]
    as_is = src.image is not None and suffix in (None, src.image.suffix.lower().replace(".jpeg", ".jpg"))
    image_src = src.image if cfg.export.images and as_is else None
    if calib_src is None:
        calib_src = generated_calib(K, T_cam_radar, c.crop_rows, c.full_size, c.working_size)
    generated = src.calib is None and src.label is None and src.objects_labelled
    record = f.reader.read(fid) if generated or (cfg.export.images and image_src is None) else None
    if src.label is not None:
        label = detector_label_text(src.label.read_text(), src.label_track_ids, calib_P2(calib_src),
                                    tuple(c.full_size))
    elif generated:  # the dataset's own annotation, for the generated calib's camera
        label = kitti_label_text(record.labels, T_cam_radar, full_K(K, c.crop_rows, c.full_size, c.working_size),
                                 tuple(c.full_size))
    else:
        label = None
    return calib_src, label, image_src, record


def _message(tally: _Tally, frames: int, root: Path, cfg: Config) -> str:
    """The run's one-line summary: what was written where, and what a detector's user must know."""
    n_points, n_unknown = tally.points, sum(tally.unknown_motion.values())
    no_motion, empty, unused = tally.no_motion, tally.empty, tally.unused
    return (f"exported {frames} frame(s), {n_points} points (+{tally.noise} noise) to {root} (the RCS "
            f"column in {cfg.radar.rss_unit}, the unit of the simulated {cfg.radar.name})"
            + _classes_note(tally.classes, cfg)
            + (f"; export.class_names renames {', '.join(sorted(unused))}, which no written label holds"
               if unused else "")
            + (f"; {len(no_motion)} of them without a recorded ego motion, their Doppler a stopped "
               f"car's (listed in {root / NO_MOTION_LIST})" if no_motion else "")
            + (f"; {n_unknown} of the points ({n_unknown / max(n_points, 1):.0%}), in {len(tally.unknown_motion)} "
               f"frame(s), lie on labelled objects whose velocity the dataset does not record: their "
               f"Doppler is a static object's, so a moving object's points read as parked (frames listed "
               f"in {root / UNKNOWN_OBJECT_MOTION_LIST})" if tally.unknown_motion else "")
            + (f"; {len(empty)} of them without a point (an empty .bin, on which a detector's "
               f"voxelisation may fail): {', '.join(empty[:5])}{' ...' if len(empty) > 5 else ''}"
               if empty else "")
            + (f"; {len(tally.unlabelled)} of the frames under training/ have no label_2 file (the dataset "
               f"labels none for them), which OpenPCDet's info generation needs for every train and val frame: "
               f"label them or take them out of ImageSets/train.txt and val.txt (listed in "
               f"{root / UNLABELLED_LIST})" if tally.unlabelled else "")
            + ("" if tally.lists["train"] else _no_train_hint(cfg)))


def _classes_note(classes: dict[str, Counter[str]], cfg: Config) -> str:
    """The labelled boxes per class of the training subset (a detector's CLASS_NAMES must be among
    them), or of the testing subset when no training frame has labels; '' without labels."""
    subset = "training" if classes["training"] else "testing"
    if not classes[subset]:
        return ""
    counts = ", ".join(f"{name} {n}" for name, n in classes[subset].most_common())
    renamed = f", after export.class_names = '{cfg.export.class_names}'" if cfg.export.class_names else ""
    return f"; labelled boxes under {subset}/ by class{renamed}: {counts} (a detector's CLASS_NAMES take these names)"


def _no_train_hint(cfg: Config) -> str:
    """Why the export has no frame in ImageSets/train.txt (a detector trains on none), and the way out."""
    if cfg.synth.split != "all":
        return f"; no frame of the train split (synth.split = '{cfg.synth.split}': --set synth.split=all exports every frame)"
    return (f"; no frame is in the train split (split.rule = '{cfg.split.rule}', split.fractions = "
            f"{','.join(f'{x:g}' for x in cfg.split.fractions)}), so OpenPCDet finds no training frame: give the "
            f"train part a share, e.g. --set split.rule=sequence --set split.fractions=0.5,0.5,0")


NO_MOTION_LIST = "ego_velocity_unknown.txt"
"""Under the export folder: the exported frames whose dataset records no ego motion (KITTI without
oxts), one id per line; absent when there are none."""


UNKNOWN_OBJECT_MOTION_LIST = "object_velocity_unknown.txt"
"""Under the export folder: the exported frames with points on labelled objects whose velocity the
dataset does not record (their Doppler is a static object's), one id per line; absent when there
are none."""


UNLABELLED_LIST = "label_missing.txt"
"""Under the export folder: the frames under training/ written without a label_2 file (the dataset
labels none for them: MSC-Rad4R, an Astyx frame without its ground-truth file), one id per line;
absent when there are none."""


def check(cfg: Config) -> None:
    """ConfigError for a malformed export.class_names (export.image_format is held to
    pipeline.config.CHOICES where set)."""
    from pipeline.export import parse_class_map

    try:
        parse_class_map(cfg.export.class_names)
    except ValueError as exc:
        raise ConfigError(f"export.class_names: {exc}") from None


STAGE = DatasetStage(name="export", upstream=("calibrate", "synthesize"), config_keys=CONFIG_KEYS, run=run,
                     version=VERSION, doc=__doc__, check=check, local_files=True)
