"""Configuration: one profile per dataset (TOML files shipped in ``pipeline/profiles``), typed
sections, overrides with ``--set section.key=value`` and environment variables.

Environment overrides: ``PIPELINE__SECTION__KEY=value`` (double underscores), e.g.
``PIPELINE__TRAIN__EPOCHS=3``. Precedence: defaults < profile < environment < --set.
Every key is addressed as ``section.key``; ``Config.get("heatmap.sigma_px")`` returns its value and
``Config.fingerprint(keys)`` hashes a set of keys for the cache.
"""

from __future__ import annotations

import ast
import dataclasses
import difflib
import functools
import hashlib
import inspect
import json
import math
import os
import textwrap
import tomllib
from dataclasses import dataclass, field, fields, replace
from importlib import resources
from typing import Any, get_type_hints

from pipeline.errors import ConfigError


@dataclass(frozen=True)
class DatasetSection:
    """Which reader reads the raw files and how frames are named."""

    reader: str = "vod"
    """Reader module name in pipeline.readers: vod, astyx, astyx_demo, msc, kitti, synthetic."""
    description: str = ""
    """One line shown by `pipeline datasets`."""
    data_root: str = ""
    """Default data root ('' = must be given; the synthetic world generates into the cache)."""
    world_frames: int = 240
    """Synthetic world only: number of frames generated when no data root is given."""
    world_seed: int = 0
    """Synthetic world only: generator seed."""
    world_resolution: tuple[int, int] = (640, 384)
    """Synthetic world only: rendered image size (W, H) pixels."""
    world_sequence_len: int = 40
    """Synthetic world only: frames per sequence (scene types cycle from one sequence to the next)."""
    radar_mount_T_radar_lidar: tuple[float, ...] = (1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1)
    """KITTI only: row-major 4x4 transform from the lidar frame to the simulated radar {D}."""
    follow_links: bool = False
    """Astyx only: index entries may lead through symbolic links inside the data root to files
    elsewhere (sensor folders linked to other storage). Off: an entry leading out of the root is
    refused, as one from an untrusted index could; entries that are absolute or climb out with '..'
    are refused either way. It changes which frames can be read, not what is read from them, so it
    is in no fingerprint: frames refused before need ``--retry-failed``."""
    msc_doppler_field: str = "doppler"
    """MSC-Rad4R only: the radar point field read as the Doppler, m/s: 'doppler' or 'power' (the other is the RSS)."""


@dataclass(frozen=True)
class RadarSection:
    """The radar being learned / simulated (its profile)."""

    name: str = "ZF FRGen21"
    """Radar model, for reports."""
    az_res_deg: float = 1.5
    """Azimuth resolution delta_1, degrees."""
    el_res_deg: float = 1.5
    """Elevation resolution delta_2, degrees."""
    fov_az_deg: float = 64.0
    """Total horizontal field of view, degrees (symmetric about x)."""
    fov_el_deg: float = 40.0
    """Total vertical field of view, degrees (symmetric about the xy plane)."""
    max_range_m: float = 50.0
    """Radar points farther than this are dropped everywhere, metres."""
    max_points: int = 1000
    """Dis-Net count scale: n_hat = sigmoid(.) * max_points."""
    store_max_points: int = 4096
    """Capacity of the per-frame radar arrays in the cache; more points is a frame error."""
    rss_min: float = -74.0
    """Lower end of the RSS range (dataset units), normalises L_a."""
    rss_max: float = 39.8
    """Upper end of the RSS range (dataset units)."""
    rss_unit: str = "dBsm"
    """Unit of the RSS column, for reports."""
    doppler_sign: int = 1
    """Dataset Doppler = doppler_sign * range rate: +1 VoD (negative approaching), -1 Astyx."""
    doppler_span_mps: float = 0.0
    """Unambiguous Doppler span, m/s (0 = no aliasing; Astyx 6455: 10.39)."""


@dataclass(frozen=True)
class CameraSection:
    """Working resolution: images are cropped (full-resolution rows) then resized."""

    full_size: tuple[int, int] = (1936, 1216)
    """Native image size (W, H), pixels."""
    crop_rows: tuple[int, int] = (0, 1216)
    """Rows [top, bottom) of the full-resolution image kept (rows the radar cannot see dropped)."""
    working_size: tuple[int, int] = (320, 160)
    """Image size (W, H) the networks see, pixels; multiples of 32."""


@dataclass(frozen=True)
class LidarSection:
    """Lidar storage in the cache."""

    store_max_points: int = 65536
    """Capacity of the per-frame lidar arrays; lidar outside the camera view or beyond
    max_range_m + margin is dropped before storing, then points are subsampled if still over."""
    range_margin_m: float = 10.0
    """Lidar kept up to radar.max_range_m + this margin, metres."""


@dataclass(frozen=True)
class SplitSection:
    """Train / val / test assignment of frames."""

    rule: str = "block"
    """'sequence' (whole sequences), 'block' (blocks of consecutive frames), or 'random'
    (the paper's within-sequence shuffle; leaks neighbouring frames)."""
    fractions: tuple[float, float, float] = (0.6, 0.1, 0.3)
    """Train, val, test shares."""
    block_len: int = 15
    """Frames per block for rule 'block'."""
    seed: int = 0
    """Seed of the assignment."""


@dataclass(frozen=True)
class HeatmapSection:
    """Ground-truth heatmap (eqs. 5-7)."""

    sigma_px: tuple[float, float] = (100.0, 100.0)
    """Standard deviations (u, v) of the diagonal Sigma in full-resolution pixels."""


@dataclass(frozen=True)
class PatchesSection:
    """RSS-Net training samples (eqs. 17-21)."""

    points_per_frame: int = 50
    """Radar points sampled per frame (VoD 50, Astyx/MSC 100)."""
    r_c_px: float = 50.0
    """Half side of the image patch in full-resolution pixels."""
    r_l_m: float = 1.0
    """Radius of the lidar neighbourhood for the local range image, metres."""
    range_image_size: tuple[int, int] = (128, 32)
    """Local range image (w, h), pixels."""
    patch_size_px: int = 32
    """Side of the stored image patch after resizing to the network input, pixels."""
    seed: int = 0
    """Seed of the point sampling (seeded once per run, not per frame)."""


@dataclass(frozen=True)
class PlacementSection:
    """Lidar-point placement (pipeline.placement): PlaceNet's training rows and architecture, and how
    points are chosen when synth.placement = 'lidar'."""

    points_per_frame: int = 2048
    """Lidar candidates per frame sampled (uniformly, seeded by patches.seed and the frame) as
    PlaceNet training rows by the patches stage."""
    gate_m: float = 1.0
    """A real radar point counts for its nearest lidar candidate only within this distance, metres."""
    width: int = 64
    """Units per hidden layer."""
    depth: int = 2
    """Hidden layers."""
    lr: float = 2e-3
    """Adam learning rate of PlaceNet (a small MLP: train.lr is Dis-Net's and RSS-Net's)."""
    batch_size: int = 4096
    """Candidates per batch."""
    epochs: int = 32
    """PlaceNet's epochs (train.epochs is Dis-Net's and RSS-Net's; a PlaceNet epoch takes about a
    second). At the 8-12 epochs of train.epochs it was undertrained: at 32 the val NLL fell on
    both worlds and F1 rose on three of the four val and test splits (docs/EXPERIMENTS.md, "PlaceNet epochs");
    the best epoch came before 32 on both, and 64 or 128 chose the same weights."""
    patience: int = 0
    """Stop PlaceNet's training once this many epochs in a row have not lowered its val loss (its
    training loss without val frames); 0: train all placement.epochs (as train.patience is for
    Dis-Net and RSS-Net). On Astyx its val NLL is flat from epoch 10 on (0.3941 there, 0.3928 at
    epoch 31, the best of 32): a patience up to 6 would stop it by epoch 16 with epoch 10 best."""
    voxel_m: float = 0.0
    """Spread the synthetic points over cubes of this side, metres: a cube gets a second point only
    once every cube holding a candidate has one (0: no spreading). Off by default: on Astyx, whose
    radar returns crowd together, any spreading lowered F1 (0.5 m: 0.310 -> 0.275); on the synthetic
    world 1 m changed F1 by +0.007."""
    map_weight: float = 0.5
    """Exponent beta of the map in the placement weights q = lambda * (G * (M / Z)) ** beta
    (pipeline.placement), 0..1: 1 lets the map decide each image region's share of the points and
    PlaceNet only which candidates inside it; 0 ignores the map. 0.5 was chosen on the val splits
    (docs/EXPERIMENTS.md, "Map weight"): on Astyx F1 0.316 at 1, 0.323 at 0.5, 0.327 at 0; on the demo world
    0.284, 0.289, 0.289."""


@dataclass(frozen=True)
class DisNetSection:
    """Dis-Net architecture."""

    use_speed: bool = True
    """Feed the ego speed to the number branch (Table II ablation)."""
    backbone_weights: str = ""
    """Path of a local torchvision ResNet-18 state dict ('' = random init)."""
    width: int = 64
    """Base width of the ResNet-18 (64 = standard)."""
    prior: bool = True
    """Add log(mean training heatmap) to the map logits and start the count at the training mean
    count (or at the frame's speed: ``speed_count_prior``), learning the residuals (an improvement
    over the paper: training starts at the mean-map and mean-count baselines; False = the paper's
    network)."""
    prior_mix: str = "off"
    """With ``prior``: 'val' mixes a share w of the prior (the mean training map) into Dis-Net's
    map, (1 - w) map + w prior, w in 0, 0.05, ..., 1 chosen after training for the lowest mean L_KL
    on the val split (recorded in the checkpoint; 0 without val frames); 'off' (the default): the
    network's map as it is. L_KL is convex, so the mixture of two maps wrong in different places can
    beat both: on 2026-12-06 test L_KL 0.316 -> 0.285 on the demo world (w = 0.5; the mean map
    0.310) and 0.281 -> 0.264 on Astyx (w = 0.2; the mean map 0.253), while Chamfer, GOSPA and F1
    moved within 0.01 and 0.2 m either way (docs/EXPERIMENTS.md, "The prior mixed into the map")."""
    speed_count_prior: bool = False
    """With ``prior`` and ``use_speed``: start the count at the training mean count AT THE FRAME'S
    EGO SPEED (``pipeline.net_baselines.speed_count_prior``: a knot for a stopped ego, speed quantiles
    of at least 30 frames for the rest, linear between) instead of the overall mean; the number
    branch learns the per-frame deviation from it. A radar's count depends strongly on its speed
    (static returns at zero Doppler when stopped). For large training sets: on the 2400-frame
    world it cut test L_n from 0.258 to 0.052, on the 240-frame demo it made L_n and L_KL worse
    (docs/EXPERIMENTS.md). False = one mean count (the default)."""
    speed_map: bool = False
    """Also give the ego speed to the distribution branch (per-channel scale and shift of the
    features it decodes): one image cannot tell a stopped ego from a moving one, yet the radar's
    static returns depend on it. False = the paper (speed feeds the number branch only)."""
    skips: bool = False
    """Decode the map from the backbone's 1/16, 1/8 and 1/4 features as well as the 1/32 ones
    (U-Net / FPN lateral connections), so local appearance (material, shape) reaches the map.
    False = the paper (the distribution branch sees the 1/32 features only)."""


@dataclass(frozen=True)
class RssNetSection:
    """RSS-Net architecture and its inputs (Table III ablation)."""

    use_camera: bool = True
    """Use the image patch branch."""
    use_lidar: bool = True
    """Use the local range image branch."""
    use_radar_point: bool = True
    """Use the point vector [x, y, z, v]."""


@dataclass(frozen=True)
class TrainSection:
    """Training of the networks."""

    nets: str = "disnet,rssnet,placenet"
    """Comma-separated nets to train (placenet: needed by synth.placement = 'lidar')."""
    nets_from: str = ""
    """Another dataset under the same cache root whose trained nets this one uses instead of
    training its own (e.g. 'astyx' for KITTI, which has no radar): the train stage takes its
    checkpoints, and its radar and RSS-Net input settings replace this profile's
    (pipeline.transfer). '' (default): train on this dataset."""
    epochs: int = 20
    """Epochs per net."""
    checkpoint_every_s: float = 600.0
    """Inside an epoch, every net saves a resume point after the first window of batches
    (pipeline.rows.WINDOW_BATCHES) that ends this many seconds or more after its last save, so a
    run killed in a long epoch (tens of thousands of frames) resumes from there, to the weights an
    uninterrupted run gives; 0: only at the end of each epoch. No training key: it changes when the
    last checkpoint is written, not what is learned."""
    patience: int = 0
    """Early stopping of Dis-Net and RSS-Net: a net stops once this many epochs in a row have not
    lowered its selection loss (train.select_on, on the val frames, or the training frames without
    any); its best epoch is kept as always. 0: train all train.epochs (the paper). Changing it
    continues a finished net where that gives what a fresh run would, and retrains it where the
    best epoch lies beyond where a fresh run would have stopped (pipeline.continuation)."""
    lr: float = 1e-4
    """Adam learning rate."""
    batch_size: int = 4
    """Dis-Net batch size (frames)."""
    rss_batch_size: int = 256
    """RSS-Net batch size (points)."""
    alpha: float = 1.0
    """Weight of L_n in L = L_KL + alpha L_n."""
    count_grad_scale: float = 1.0
    """Dis-Net: factor on the gradient that L_n sends from the number branch into the shared
    backbone (1: the paper; 0: the backbone learns from L_KL only, the number branch still from
    L_n). Forward values are unchanged."""
    count_refit_epochs: int = 0
    """Dis-Net: after training, refit the number branch alone on the best epoch's frozen backbone
    features for this many passes over the training frames (Adam, train.lr, train.batch_size),
    keeping the pass with the lowest val L_n (pass 0: the weights as trained); 0: off (the paper).
    The map is unchanged. Holds the pooled features of the train and val frames in memory
    (C x 90 floats per frame, 184 kB at disnet.width 64)."""
    lr_schedule: str = "constant"
    """'constant' (the paper) or 'cosine': epoch e of E trains at lr (1 + cos(pi (e - 1) / E)) / 2."""
    weight_decay: float = 0.0
    """Decoupled weight decay (AdamW); 0 is plain Adam, the paper's optimiser."""
    flip: bool = False
    """Dis-Net augmentation: mirror image and target map left-right, each frame with probability 1/2."""
    cutmix: float = 0.0
    """Dis-Net augmentation: probability per frame of pasting a random box of another frame of the
    batch, targets mixed accordingly (pipeline.augment.cutmix); 0: off (the paper)."""
    jitter: float = 0.0
    """Dis-Net augmentation: per-frame brightness and contrast factors from U(1 - jitter, 1 + jitter)
    (pipeline.augment.photometric); 0: off (the paper)."""
    map_dropout: float = 0.0
    """Dis-Net: in training, drop whole channels of the features the distribution branch decodes
    with this probability (spatial dropout); 0: off (the paper)."""
    ema_decay: float = 0.0
    """Both nets: validate, select and save an exponential moving average of the weights, updated
    after every optimiser step with this decay (e.g. 0.95); 0: the trained weights (the paper)."""
    select_on: str = "loss"
    """Which validation loss picks a net's best epoch: 'loss' (the training objective, Dis-Net's
    L_KL + alpha L_n) or 'kl' (Dis-Net's L_KL alone: its map; RSS-Net keeps its L_a)."""
    seed: int = 0
    """Seed of initialisation and shuffling."""
    device: str = "auto"
    """'auto' (CUDA when present), 'cpu' or 'cuda'."""
    threads: int = 2
    """torch CPU threads."""


TRAINING_KEYS: dict[str, tuple[str, ...]] = {
    "common": ("train.lr", "train.seed", "train.weight_decay", "train.lr_schedule", "train.ema_decay",
               "train.select_on"),
    "disnet": ("disnet.use_speed", "disnet.backbone_weights", "disnet.width", "disnet.prior",
               "disnet.speed_count_prior", "disnet.speed_map", "disnet.skips", "radar.max_points",
               "camera.working_size", "train.batch_size", "train.alpha", "train.flip", "train.count_grad_scale",
               "train.cutmix", "train.count_refit_epochs", "train.jitter", "train.map_dropout"),
    "rssnet": ("rssnet.use_camera", "rssnet.use_lidar", "rssnet.use_radar_point", "radar.rss_min",
               "radar.rss_max", "patches.patch_size_px", "patches.range_image_size", "train.rss_batch_size"),
    "placenet": ("placement.width", "placement.depth", "placement.lr", "placement.batch_size"),
}
"""The config keys that change what a net learns ('common' to every net; not epochs, device or
threads): each net's checkpoint fingerprint and the train stage's config keys are built from them."""

EPOCHS_KEYS: dict[str, str] = {"disnet": "train.epochs", "rssnet": "train.epochs", "placenet": "placement.epochs"}
"""The config key holding each net's number of epochs (PlaceNet's epochs take about a second, so it
has its own)."""
PATIENCE_KEYS: dict[str, str] = {"disnet": "train.patience", "rssnet": "train.patience",
                                 "placenet": "placement.patience"}
"""The config key holding each net's early-stopping patience (0: none), beside its epochs."""


@dataclass(frozen=True)
class SynthSection:
    """4D signal generation."""

    split: str = "test"
    """Frames to synthesize: 'train', 'val', 'test' or 'all'."""
    range_estimator: str = "nearest"
    """'mean' (paper, eqs. 13-15), 'nearest' (angularly nearest lidar point), 'median' or
    'min' over the angular window."""
    no_support: str = "widen"
    """Where no lidar point lies in the window: 'widen' (double the window up to 4 times, then
    drop) or 'drop'."""
    seed: int = 0
    """Seed of the sampling."""
    sampling: str = "systematic"
    """How pixels are drawn from the map: 'systematic' (one stratified draw: every sample still
    follows the map, with less clumping) or 'iid' (independent draws, the paper)."""
    refill_rounds: int = 3
    """Draw replacements for samples dropped (no lidar support, outside the field of view, beyond
    the maximum range) up to this many more times, so that n_hat points come out; 0: the paper's
    single draw (about 15% fewer points than n_hat on the synthetic world)."""
    count: str = "predicted"
    """'predicted' (the geometric mean of Dis-Net's count and PlaceNet's with synth.placement = lidar
    and nets trained on this dataset; Dis-Net's with ray or train.nets_from), 'disnet' (Dis-Net's
    alone, the paper) or 'oracle' (the real count, for evaluation)."""
    placement: str = "lidar"
    """Where a sampled point goes: 'lidar' (onto a lidar point chosen by the map and PlaceNet's
    intensity, pipeline.placement; an improvement over the paper) or 'ray' (the paper: on the
    pixel's camera ray at the lidar range of its angular window, synth.range_estimator)."""
    rss_sampling: str = "mean"
    """A synthesized point's RSS: 'mean' (RSS-Net's prediction, the paper) or 'residual' (plus a
    residual drawn from RSS-Net's real-minus-predicted RSS on the validation points, kept in its
    checkpoint, clipped to radar.rss_min..rss_max): the real radar's RSS spread, at the cost of
    per-point accuracy (README, "RSS spread")."""
    device: str = "cpu"
    """Where synthesize and evaluate run the nets: 'cpu', 'cuda' or 'auto' (CUDA when present). The
    CPU by default: on a 16-core GPU machine dask workers running the nets on the CPU were as fast
    (README, "On a GPU"), and CPU results are the same on every machine. No fingerprint holds it: a
    GPU rounds differently (TF32 convolutions), so the points differ in detail, not in kind."""


@dataclass(frozen=True)
class ExportSection:
    """Detector-ready output."""

    noise_fraction: float = 0.0
    """Share of uniform noise points added (paper Table IV: 0.05)."""
    pcd: bool = True
    """Also write PCD files."""
    previews: bool = True
    """Write a preview PNG per frame."""
    images: bool = True
    """Write image_2/<id> beside each frame (OpenPCDet reads the image size from it)."""
    image_format: str = "source"
    """source: the dataset's own image file as it is (VoD .jpg, KITTI .png), else the reader's image
    as PNG; png or jpg: that format for every frame (OpenPCDet's KITTI loader opens .png, the
    View-of-Delft forks .jpg)."""
    class_names: str = ""
    """Classes renamed in the written labels, 'From=To,...' (e.g. 'Person=Pedestrian' for Astyx's
    people under the name OpenPCDet's configurations use); '': the dataset's own names."""


@dataclass(frozen=True)
class EvalSection:
    """Fidelity evaluation."""

    split: str = "test"
    """Split evaluated: 'train', 'val', 'test' or 'all' (its frames that synthesize finished)."""
    figure_frames: int = 4
    """Frames drawn in the Fig. 8-style figure."""
    gate_m: float = 1.0
    """Matched-F1 distance gate, metres."""
    gate_rss: float = 8.0
    """Matched-F1 RSS gate, dataset units."""
    gate_doppler_mps: float = 2.5
    """Matched-F1 Doppler gate, m/s."""
    pooled_rows_max: int = 4_000_000
    """Per-point rows of one kind the report pools over every evaluated frame (every method's points
    and the real ones; the physics checks' residuals) for its distribution distances, histograms and
    physics checks; above it a random sample of about this many, and the report says so. 4,000,000 rows of
    points take 192 MB (the demo world's test split pools about 90,000)."""


@dataclass(frozen=True)
class RunSection:
    """Execution."""

    workers: int = 2
    """dask worker processes of the local cluster (1 = in-process serial loop)."""
    staging_dir: str = "~/.cache/radarsim-pipeline"
    """Local folder for the stages that write with local file APIs (train, export, evaluate; and
    `pipeline ablate`) on a remote (fsspec) cache: each writes into a local staging folder here and uploads it when it
    finishes; readers of their output keep a local copy here (pipeline.dirstore.DirStore.local_copy)."""
    checkpoint_upload_s: float = 60.0
    """On a remote (fsspec) cache, seconds between train's uploads of its checkpoints while it
    trains: at the end of an epoch at least this long after the last upload, the net's best and last
    checkpoints are uploaded, so that a train killed on one machine resumes from that epoch on any
    other (0: after every epoch). Outputs do not depend on it."""
    progress_every_s: float = 60.0
    """Where stderr is not a terminal (a log file, a batch job's output), seconds between progress
    lines of long work (a stage's frames, a training epoch, the world's generation): each says how
    far it is and about how long is left, and an epoch's line its losses; work shorter than this
    writes none (0: no progress lines). On a terminal the progress bars are drawn instead."""


SECTIONS: dict[str, type] = {
    "dataset": DatasetSection,
    "radar": RadarSection,
    "camera": CameraSection,
    "lidar": LidarSection,
    "split": SplitSection,
    "heatmap": HeatmapSection,
    "patches": PatchesSection,
    "placement": PlacementSection,
    "disnet": DisNetSection,
    "rssnet": RssNetSection,
    "train": TrainSection,
    "synth": SynthSection,
    "export": ExportSection,
    "eval": EvalSection,
    "run": RunSection,
}


ADDED_KEYS: dict[str, Any] = {"synth.rss_sampling": "mean", "disnet.prior_mix": "off",
                             "dataset.msc_doppler_field": "doppler", "train.patience": 0, "placement.patience": 0}
"""Keys added to stages' fingerprints after outputs were made, with the value those outputs were
made with: at that value a key is left out of the fingerprint, so adding it recomputes nothing."""


READER_KEYS: dict[str, str] = {"dataset.world_frames": "synthetic", "dataset.world_seed": "synthetic",
                               "dataset.world_resolution": "synthetic", "dataset.world_sequence_len": "synthetic",
                               "dataset.radar_mount_T_radar_lidar": "kitti", "dataset.msc_doppler_field": "msc"}
"""Keys that only one reader (dataset.reader) uses: under another, a fingerprint takes them at their
defaults, so that setting one (PIPELINE__DATASET__WORLD_FRAMES for `make demo-large`, say) leaves
that dataset's outputs current (since 2026-12-06; before, it recomputed them from calibrate on)."""


@dataclass(frozen=True)
class Config:
    """A complete configuration: the profile name plus one frozen section per concern."""

    profile: str
    dataset: DatasetSection = field(default_factory=DatasetSection)
    radar: RadarSection = field(default_factory=RadarSection)
    camera: CameraSection = field(default_factory=CameraSection)
    lidar: LidarSection = field(default_factory=LidarSection)
    split: SplitSection = field(default_factory=SplitSection)
    heatmap: HeatmapSection = field(default_factory=HeatmapSection)
    patches: PatchesSection = field(default_factory=PatchesSection)
    placement: PlacementSection = field(default_factory=PlacementSection)
    disnet: DisNetSection = field(default_factory=DisNetSection)
    rssnet: RssNetSection = field(default_factory=RssNetSection)
    train: TrainSection = field(default_factory=TrainSection)
    synth: SynthSection = field(default_factory=SynthSection)
    export: ExportSection = field(default_factory=ExportSection)
    eval: EvalSection = field(default_factory=EvalSection)
    run: RunSection = field(default_factory=RunSection)

    def get(self, key: str) -> Any:
        """Value of a dotted key such as 'heatmap.sigma_px'; ConfigError (with a suggestion) if unknown."""
        section, name = _split_key(key)
        return getattr(getattr(self, section), name)

    def fingerprint(self, keys: tuple[str, ...] | list[str]) -> str:
        """Stable hash (16 hex digits) of the values of ``keys``; a key of ADDED_KEYS at the value
        it names is left out (outputs made before the key existed stay current), a key of
        READER_KEYS under another reader taken at its default."""
        values = {k: self._fingerprinted(k) for k in sorted(keys)}
        payload = json.dumps({k: jsonable(v) for k, v in values.items()
                              if k not in ADDED_KEYS or v != ADDED_KEYS[k]}, sort_keys=True)
        return hashlib.sha256(payload.encode()).hexdigest()[:16]

    def _fingerprinted(self, key: str) -> Any:
        """The value of ``key`` that a fingerprint takes (READER_KEYS)."""
        if key in READER_KEYS and READER_KEYS[key] != self.dataset.reader:
            section, name = _split_key(key)
            return getattr(SECTIONS[section](), name)
        return self.get(key)

    def with_overrides(self, overrides: dict[str, str]) -> "Config":
        """A copy with ``{'section.key': 'text value'}`` applied (values parsed by the field type)."""
        cfg = self
        for key, text in overrides.items():
            section, name = _split_key(key)
            sec = getattr(cfg, section)
            value = _parse_value(key, text, get_type_hints(type(sec))[name])
            check_limit(key, value)
            cfg = replace(cfg, **{section: replace(sec, **{name: value})})
        return cfg

    def to_dict(self) -> dict[str, dict[str, Any]]:
        """Plain nested dict (JSON-able)."""
        return {s: {k: jsonable(v) for k, v in dataclasses.asdict(getattr(self, s)).items()} for s in SECTIONS}


LIMITS: dict[str, str] = {
    "dataset.world_frames": ">0", "dataset.world_resolution": ">0", "dataset.world_sequence_len": ">0",
    "radar.az_res_deg": ">0", "radar.el_res_deg": ">0", "radar.fov_az_deg": ">0", "radar.fov_el_deg": ">0",
    "radar.max_range_m": ">0", "radar.max_points": ">0", "radar.store_max_points": ">0",
    "radar.doppler_sign": "sign", "radar.doppler_span_mps": ">=0",
    "camera.full_size": ">0", "camera.crop_rows": ">=0", "camera.working_size": ">0",
    "lidar.store_max_points": ">0", "lidar.range_margin_m": ">=0",
    "split.fractions": ">=0", "split.block_len": ">0",
    "heatmap.sigma_px": ">0",
    "patches.points_per_frame": ">0", "patches.r_c_px": ">0", "patches.r_l_m": ">0", "patches.range_image_size": ">0",
    "patches.patch_size_px": ">0",
    "placement.points_per_frame": ">0", "placement.gate_m": ">0", "placement.width": ">0", "placement.depth": ">0",
    "placement.lr": ">0", "placement.batch_size": ">0", "placement.epochs": ">=0", "placement.voxel_m": ">=0",
    "placement.map_weight": "[0,1]", "placement.patience": ">=0",
    "disnet.width": ">0",
    "train.epochs": ">=0", "train.lr": ">0", "train.batch_size": ">0", "train.rss_batch_size": ">0", "train.alpha": ">=0",
    "train.patience": ">=0", "train.checkpoint_every_s": ">=0",
    "train.count_grad_scale": "[0,1]", "train.count_refit_epochs": ">=0", "train.weight_decay": ">=0",
    "train.cutmix": "[0,1]", "train.jitter": "[0,1]", "train.map_dropout": "[0,1)", "train.ema_decay": "[0,1)",
    "train.threads": ">0",
    "synth.refill_rounds": ">=0",
    "export.noise_fraction": ">=0",
    "eval.figure_frames": ">=0", "eval.pooled_rows_max": ">0", "eval.gate_m": ">0 or inf", "eval.gate_rss": ">0 or inf",
    "eval.gate_doppler_mps": ">0 or inf",
    "run.workers": ">0",
    "run.checkpoint_upload_s": ">=0", "run.progress_every_s": ">=0",
    "dataset.world_seed": ">=0", "split.seed": ">=0", "patches.seed": ">=0", "train.seed": ">=0", "synth.seed": ">=0",
    "dataset.radar_mount_T_radar_lidar": "finite", "radar.rss_min": "finite", "radar.rss_max": "finite",
}
"""The values each numeric key may take (every item of a tuple): '>0' and '>=0' finite, '>0 or inf'
(a gate that inf turns off), '[0,1]' and '[0,1)' intervals, 'sign' +1 or -1, 'finite'. Checked wherever a value is set (profile, environment, --set),
so that a setting no stage could run with is refused before any output is touched."""

_LIMIT_TESTS: dict[str, tuple[str, Any]] = {
    ">0": ("finite and > 0", lambda v: math.isfinite(v) and v > 0),
    ">=0": ("finite and >= 0", lambda v: math.isfinite(v) and v >= 0),
    ">0 or inf": ("> 0 (inf: no gate)", lambda v: v > 0),
    "[0,1]": ("in [0, 1]", lambda v: 0 <= v <= 1),
    "[0,1)": ("in [0, 1)", lambda v: 0 <= v < 1),
    "sign": ("+1 or -1", lambda v: v in (1, -1)),
    "finite": ("finite", math.isfinite),
}


def check_relations(cfg: "Config") -> None:
    """ConfigError for settings that are each within :data:`LIMITS` but do not fit together."""
    top, bottom = cfg.camera.crop_rows
    if not 0 <= top < bottom <= cfg.camera.full_size[1]:
        raise ConfigError(f"'camera.crop_rows' must satisfy 0 <= top < bottom <= camera.full_size height "
                          f"{cfg.camera.full_size[1]}, got {top},{bottom}")
    if abs(sum(cfg.split.fractions) - 1.0) > 1e-6:
        raise ConfigError(f"'split.fractions' (train, val, test) must sum to 1, got {_text(cfg.split.fractions)}")
    mount = cfg.dataset.radar_mount_T_radar_lidar
    if len(mount) != 16:
        raise ConfigError(f"'dataset.radar_mount_T_radar_lidar' must be 16 values (a row-major 4x4 rigid transform, "
                          f"lidar -> radar), got {len(mount)}")
    from pipeline.geometry import invert_transform  # numpy: only here

    try:
        invert_transform([mount[row * 4:row * 4 + 4] for row in range(4)])
    except ValueError as exc:
        raise ConfigError(f"'dataset.radar_mount_T_radar_lidar' is not a rigid transform: {exc}") from None
    if not cfg.radar.rss_min < cfg.radar.rss_max:
        raise ConfigError(f"'radar.rss_min' must be below 'radar.rss_max', got {cfg.radar.rss_min:g} and "
                          f"{cfg.radar.rss_max:g}")


SPLIT_CHOICES = ("train", "val", "test", "all")
"""The values of a key naming the frames a stage works on: a split, or every frame."""

CHOICES: dict[str, tuple[str, ...]] = {
    "dataset.msc_doppler_field": ("doppler", "power"),
    "split.rule": ("sequence", "block", "random"),
    "disnet.prior_mix": ("off", "val"),
    "train.lr_schedule": ("constant", "cosine"),
    "train.select_on": ("loss", "kl"),
    "synth.split": SPLIT_CHOICES,
    "synth.range_estimator": ("mean", "nearest", "median", "min"),
    "synth.no_support": ("widen", "drop"),
    "synth.sampling": ("iid", "systematic"),
    "synth.count": ("predicted", "disnet", "oracle"),
    "synth.placement": ("lidar", "ray"),
    "synth.rss_sampling": ("mean", "residual"),
    "export.image_format": ("source", "png", "jpg"),
    "eval.split": SPLIT_CHOICES,
}
"""The values each text key of this table may take, checked where :data:`LIMITS` are (profile,
environment, --set), so that a misspelt one is refused by every command, whichever stages it runs.
The modules that act on a key take its tuple from here. Devices are not listed: 'cuda:1' and the
like are checked against the machine (:func:`check_device`)."""


def check_device(key: str, device: str) -> None:
    """ConfigError when ``device``, the value of ``key`` (train.device, synth.device), names no
    device this machine has; torch (1-3 s to import) only for one other than 'auto' and 'cpu',
    which need no check (pipeline.inference.select_device)."""
    if device not in ("auto", "cpu"):
        from pipeline.inference import select_device

        select_device(device, key)


def check_limit(key: str, value: Any) -> None:
    """ConfigError when ``value`` of ``key`` is outside its :data:`LIMITS` or :data:`CHOICES` (none: accepted)."""
    if key in CHOICES and value not in CHOICES[key]:
        near = difflib.get_close_matches(str(value).lower(), CHOICES[key], n=1, cutoff=0.6)
        hint = f"; did you mean '{near[0]}'?" if near else ""
        raise ConfigError(f"'{key}' must be one of {', '.join(CHOICES[key])}, got '{value}'{hint}")
    limit = LIMITS.get(key)
    if limit is None:
        return
    text, ok = _LIMIT_TESTS[limit]
    items = value if isinstance(value, tuple) else (value,)
    if not all(ok(v) for v in items):
        each = " (each value)" if isinstance(value, tuple) else ""
        raise ConfigError(f"'{key}' must be {text}{each}, got {_text(value)}")


def _text(value: Any) -> str:
    return ",".join(f"{v:g}" for v in value) if isinstance(value, tuple) else f"{value:g}"


def all_keys() -> list[str]:
    """Every valid dotted key."""
    return [f"{s}.{f.name}" for s, cls in SECTIONS.items() for f in fields(cls)]


_KEYS = all_keys()
_KEY_OF_VARIABLE = {f"PIPELINE__{k.replace('.', '__').upper()}": k for k in _KEYS}
_KEY_OF_LOWER = {k.lower(): k for k in _KEYS}


def _split_key(key: str) -> tuple[str, str]:
    if "." in key:
        section, name = key.split(".", 1)
        if section in SECTIONS and name in {f.name for f in fields(SECTIONS[section])}:
            return section, name
    near = difflib.get_close_matches(key.lower(), list(_KEY_OF_LOWER), n=1, cutoff=0.5)  # any case, as --set's
    hint = f"; did you mean '{_KEY_OF_LOWER[near[0]]}'?" if near else ""
    raise ConfigError(f"unknown configuration key '{key}'{hint}")


def jsonable(value: Any) -> Any:
    """A configuration value as JSON holds it (tuples as lists)."""
    return list(value) if isinstance(value, tuple) else value


_EXPECTED = {int: "a whole number", float: "a number", bool: "true or false"}
"""How a bad value's message names the type it should have been."""


def _parse_value(key: str, value: Any, typ: Any) -> Any:
    """Coerce a TOML value or a command-line string to the field's type."""
    text_type = str(typ)
    try:
        if typ is bool:
            if isinstance(value, bool):
                return value
            low = str(value).strip().lower()
            if low in ("1", "true", "yes", "on"):
                return True
            if low in ("0", "false", "no", "off"):
                return False
            raise ValueError(value)
        if typ is int:
            if isinstance(value, bool) or (isinstance(value, float) and not value.is_integer()):
                raise ValueError(value)
            return int(value)
        if typ is float:
            return float(value)
        if typ is str:
            return str(value)
        if text_type.startswith("tuple"):
            items = value if isinstance(value, (list, tuple)) else [v for v in str(value).replace("x", ",").split(",") if v.strip()]
            inner = typ.__args__
            if len(inner) == 2 and inner[1] is Ellipsis:
                return tuple(_parse_value(key, v, inner[0]) for v in items)
            if len(items) != len(inner):
                raise ValueError(f"expected {len(inner)} values")
            return tuple(_parse_value(key, v, t) for v, t in zip(items, inner))
    except (TypeError, ValueError) as exc:
        expected = "comma-separated values" if text_type.startswith("tuple") else _EXPECTED.get(typ, text_type)
        detail = f": {exc}" if text_type.startswith("tuple") else ""  # Python's own words add nothing for one value
        raise ConfigError(f"bad value {value!r} for '{key}' (expected {expected}){detail}") from None
    raise ConfigError(f"'{key}': unsupported field type {text_type}")


def named_nets(cfg: "Config") -> set[str]:
    """The nets train.nets names (checked against the known ones by the train stage)."""
    return {n.strip() for n in cfg.train.nets.split(",") if n.strip()}


def own_radar(cfg: "Config") -> "RadarSection":
    """The radar the dataset itself recorded, as its reader reads it (Doppler sign and span, field
    of view): ``cfg.radar``, except where train.nets_from put another dataset's radar settings into
    ``cfg`` (pipeline.transfer.with_nets_from): then the dataset profile's own (without environment
    overrides)."""
    if not cfg.train.nets_from:
        return cfg.radar
    return _profile_radar(cfg.profile)


@functools.lru_cache(maxsize=8)
def _profile_radar(profile: str) -> "RadarSection":
    """The radar section of ``profile`` as shipped (readers and evaluate ask per frame)."""
    return load_config(profile, environ={}).radar


def profile_names() -> list[str]:
    """Names of the dataset profiles shipped in the package."""
    files = resources.files("pipeline.profiles").iterdir()
    return sorted(p.name[:-5] for p in files if p.name.endswith(".toml"))


def check_profile(name: str, setting: str = "") -> None:
    """ConfigError unless ``name`` is a dataset profile, suggesting the nearest; ``setting``: the
    config key that gave the name, if any."""
    names = profile_names()
    if name not in names:
        near = difflib.get_close_matches(name, names, n=1)
        hint = f"; did you mean '{near[0]}'?" if near else ""
        what = f"{setting} = '{name}' names no dataset profile" if setting else f"unknown dataset profile '{name}'"
        raise ConfigError(f"{what} (known: {', '.join(names)}){hint}")


def profile_values(profile: str) -> dict[str, Any]:
    """The values the profile ``profile``'s TOML sets, by dotted key (the others keep the sections'
    defaults)."""
    check_profile(profile)
    text = resources.files("pipeline.profiles").joinpath(f"{profile}.toml").read_text()
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"profile {profile}.toml: {exc}") from None
    flat: dict[str, Any] = {}
    for section, values in data.items():
        if not isinstance(values, dict):
            raise ConfigError(f"profile {profile}.toml: top-level key '{section}' is not a [section]")
        for name, value in values.items():
            flat[f"{section}.{name}"] = value
    return flat


@functools.cache
def key_docs() -> dict[str, str]:
    """Each dotted key's docstring (the string under its field in the section's class)."""
    docs = {}
    for section, cls in SECTIONS.items():
        body = ast.parse(textwrap.dedent(inspect.getsource(cls))).body[0].body
        for field_node, doc in zip(body, body[1:]):
            if (isinstance(field_node, ast.AnnAssign) and isinstance(doc, ast.Expr)
                    and isinstance(doc.value, ast.Constant) and isinstance(doc.value.value, str)):
                docs[f"{section}.{field_node.target.id}"] = inspect.cleandoc(doc.value.value)
    return docs


def load_config(profile: str, overrides: dict[str, str] | None = None,
                environ: dict[str, str] | None = None) -> Config:
    """Build the configuration of ``profile`` with environment and explicit overrides applied."""
    flat = profile_values(profile)
    cfg = Config(profile=profile)
    overrides = overrides or {}
    cfg = cfg.with_overrides(flat)
    given = {k.lower() for k in overrides}  # keys are matched ignoring case
    for key, (var, value) in _env_variables(os.environ if environ is None else environ).items():
        if key.lower() in given:  # --set wins, and is the value checked
            continue
        try:
            cfg = cfg.with_overrides({key: value})
        except ConfigError as exc:  # named as the user wrote it: the variable, not the key
            raise ConfigError(f"environment variable {var}={value!r}: {exc}") from None
    cfg = cfg.with_overrides(overrides)
    check_relations(cfg)  # once every value is in (a caller may change related keys one by one later)
    return cfg


def env_overrides(environ: dict[str, str]) -> dict[str, str]:
    """``{'section.key': value}`` of the PIPELINE__SECTION__KEY variables in ``environ``; ConfigError
    for a PIPELINE__ variable that names no key."""
    return {key: value for key, (_, value) in _env_variables(environ).items()}


def _env_variables(environ: dict[str, str]) -> dict[str, tuple[str, str]]:
    """``{'section.key': (variable, value)}`` of the PIPELINE__SECTION__KEY variables in ``environ``;
    ConfigError naming the variable (and the one meant, where it is clear) for one that names no key,
    e.g. PIPELINE__TRAIN_EPOCHS, which would otherwise be ignored without a word."""
    out = {}
    for var, value in sorted(environ.items()):
        if not var.upper().startswith("PIPELINE__"):  # the whole name in any case
            continue
        key = _KEY_OF_VARIABLE.get(var.upper())  # keys are matched ignoring case (radar_mount_T_radar_lidar)
        if key is None:
            tail = var[len("PIPELINE__"):].upper()
            meant = [k for k in _KEYS if k.replace(".", "_").upper() == tail]
            near = difflib.get_close_matches(var.upper(), list(_KEY_OF_VARIABLE), n=1, cutoff=0.8)
            meant = meant or [_KEY_OF_VARIABLE[v] for v in near]
            hint = f"did you mean {_variable(meant[0])}?" if meant else "e.g. PIPELINE__TRAIN__EPOCHS"
            raise ConfigError(f"environment variable {var} names no configuration key (the form is "
                              f"PIPELINE__SECTION__KEY, two underscores around SECTION); {hint}")
        if key in out:
            raise ConfigError(f"environment variables {out[key][0]} and {var} both set {key}: unset one")
        out[key] = (var, value)
    return out


def _variable(key: str) -> str:
    """The environment variable that sets ``key``."""
    section, name = key.split(".", 1)
    return f"PIPELINE__{section.upper()}__{name.upper()}"


def parse_set_options(items: tuple[str, ...] | list[str]) -> dict[str, str]:
    """Parse ``key=value`` strings from --set into ``{'section.key': value}``; a key is matched
    ignoring case, as the PIPELINE__ variables' are (TRAIN.EPOCHS is train.epochs), and returned as
    the configuration spells it. ConfigError on a malformed item or an unknown key (with the nearest)."""
    out: dict[str, str] = {}
    for item in items:
        if "=" not in item:
            raise ConfigError(f"--set expects key=value, got '{item}'")
        key, value = item.split("=", 1)
        key = _KEY_OF_LOWER.get(key.strip().lower(), key.strip())
        _split_key(key)
        out[key] = value.strip()
    return out
