# SPDX-License-Identifier: Apache-2.0
"""Config sections of the core: one frozen section per stage, and :class:`CoreConfig`, the
sections :class:`pugsd.core.pipeline.PugsPipeline` takes.

This module imports only the standard library, :mod:`pugsd.configbase` and :mod:`pugsd.errors`, so
that the core loads without the wire, daemon or recorder packages. :mod:`pugsd.config` collects
these sections with those of the other subsystems into the whole configuration.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from pugsd.configbase import opt
from pugsd.errors import ConfigError


def _check(cond: bool, msg: str) -> None:
    if not cond:
        raise ConfigError(msg)


@dataclass(frozen=True, slots=True)
class StereoConfig:
    """Stereo matching (OpenCV SGBM) and per-pixel depth noise."""

    downsample: int = opt(4, "image downsampling factor before matching (paper: 4)", ge=1, le=16)
    mode: str = opt("sgbm_3way", "OpenCV SGBM mode", choices=("sgbm", "sgbm_3way", "hh"))
    num_disparities: int = opt(
        0,
        "disparity search range at full resolution (scaled by downsample); 0: sized from the rig "
        "in CameraInfo to reach min_depth_m, at most half the image width (nearer than f_x B / "
        "(W / 2), 1.9 B at 56 deg HFOV, no setting measures the image centre; a nearer surface is "
        "matched at a wrong disparity, not rejected, and the log says so)",
        unit="px",
        ge=0,
        le=65520,  # the SGBM parameters are C ints; no image is wider (a multiple of 16)
    )
    min_disparity: int = opt(0, "smallest disparity searched", unit="px", ge=0, le=65535)
    block_size: int = opt(5, "SGBM block size (odd)", unit="px", ge=1, le=31)
    uniqueness_ratio: int = opt(10, "SGBM uniqueness ratio", unit="%", ge=0, le=100)
    speckle_window_size: int = opt(
        50, "SGBM speckle filter window (0 disables)", unit="px", ge=0, le=2**31 - 1
    )
    speckle_range: int = opt(2, "SGBM speckle filter disparity range", unit="px", ge=0, le=65535)
    disp12_max_diff: int = opt(1, "left-right consistency check (-1 disables)", unit="px", ge=-1, le=65535)
    min_depth_m: float = opt(
        0.2,
        "nearer depths are invalid (NaN); with num_disparities = 0 the search reaches this near",
        unit="m",
        gt=0.0,
    )
    max_depth_m: float = opt(3.0, "farther depths are invalid (NaN)", unit="m", gt=0.0)
    noise_mode: str = opt(
        "fixed",
        "per-pixel depth noise model: fixed sigma_d^2 or stereo disparity model",
        choices=("fixed", "disparity"),
    )
    sigma_d2_m2: float = opt(
        0.001,
        "fixed depth variance sigma_d^2 (paper: 0.001; noisy experiments 0.01)",
        unit="m^2",
        gt=0.0,
    )
    sigma_disp_px: float = opt(
        0.5,
        "disparity std for noise_mode=disparity, in pixels of the matched (downsampled) images: "
        "sigma_z = z^2 sigma_disp / (f B) with f the downsampled focal length",
        unit="px",
        gt=0.0,
    )

    def __post_init__(self) -> None:
        _check(self.block_size % 2 == 1, f"block_size: must be odd, got {self.block_size}")
        _check(
            self.num_disparities % 16 == 0, "num_disparities: must be 0 (auto) or a multiple of 16"
        )
        _check(self.max_depth_m > self.min_depth_m, "max_depth_m: must exceed min_depth_m")


@dataclass(frozen=True, slots=True)
class ObservationConfig:
    """Back-projection with covariance and the world transform (Eq. 1-3)."""

    covariance_form: str = opt(
        "rotated",
        "Eq. 3 form: rotated = R Sigma R^T + Sigma_t; paper_literal = Sigma + Sigma_t",
        choices=("rotated", "paper_literal"),
    )
    rotation_term: bool = opt(True, "add G Sigma_phi G^T from the 6x6 pose covariance (rotated form only)")
    regulariser_m: float = opt(
        0.0005,
        "isotropic std eps added as eps^2 I so every covariance is invertible (> 0: a pose "
        "reported without covariance leaves the needle of Eq. 2 rank 1)",
        unit="m",
        gt=0.0,
    )
    max_points_per_frame: int = opt(
        20000, "random subsample of back-projected points per frame (0 keeps all)", ge=0, le=10_000_000
    )


@dataclass(frozen=True, slots=True)
class FofConfig:
    """Fused occupancy field: Gaussian mixture, responsibilities and information fusion (Eq. 4-6)."""

    k_neighbours: int = opt(10, "K nearest world Gaussians used in Eq. 5-6", ge=1, le=64)
    voxel_size_m: float = opt(
        0.004, "voxel hash size of the point store (one fused Gaussian per voxel)", unit="m", gt=0.0
    )
    max_voxels: int = opt(
        200000, "cap on stored voxels; the oldest are evicted beyond it", ge=100, le=20_000_000
    )
    target_scale: str = opt(
        "p99",
        "divide FOF targets by their max or 99th percentile for conditioning",
        choices=("max", "p99"),
    )
    include_self: bool = opt(True, "a point counts as its own neighbour when building targets")
    fused_mean: str = opt(
        "query",
        "centre of the cubature: the query point or the information-form mean",
        choices=("query", "information"),
    )
    query_device: str = opt(
        "auto",
        "where Algorithm 1 lines 1-2 run: cpu (KD-tree, numpy), cuda (brute-force K-NN and Eq. 5-6 "
        "in torch), auto (cuda when the SVGP runs on CUDA)",
        choices=("auto", "cpu", "cuda"),
    )
    query_workers: int = opt(
        0,
        "threads for the nearest-neighbour queries of Algorithm 1 lines 1-2: -1 all cores, 0 auto "
        "(all cores when the SVGP runs on CUDA, else 1: a 2-core computer's other core trains)",
        ge=-1,
        le=1024,
    )


@dataclass(frozen=True, slots=True)
class SvgpConfig:
    """The SVGP on the FOF (Eq. 7-8) and its batch and streaming training."""

    num_inducing: int = opt(
        0,
        "inducing points M of the streaming model; 0 = auto: 250 on the CPU, 500 when the SVGP "
        "runs on CUDA (paper: 500; a CPU step costs O(M^3), a CUDA step is bound by its kernel "
        "launches rather than by M; see docs/performance.md)",
        ge=0,
        le=5000,
    )
    paper_num_inducing: int = opt(500, "inducing points in paper mode (fit_paper; paper: 500)", ge=8, le=5000)
    kernel: str = opt("rbf", "ARD kernel inside a ScaleKernel", choices=("rbf", "matern52"))
    variance: str = opt(
        "latent",
        "predictive variance of the latent f or of the observation y",
        choices=("latent", "observed"),
    )
    device: str = opt("cpu", "torch device; auto uses CUDA when present", choices=("cpu", "cuda", "auto"))
    dtype: str = opt("float32", "torch dtype", choices=("float32", "float64"))
    seed: int = opt(0, "random seed for inducing points and minibatches", ge=0)
    paper_lr: float = opt(1e-3, "Adam learning rate in paper mode (paper: 1e-3)", gt=0.0)
    paper_epochs: int = opt(100, "epochs in paper mode (paper: 100)", ge=1)
    batch_size: int = opt(1024, "minibatch size", ge=16, le=1_000_000)
    lengthscale_init_m: float = opt(0.02, "initial ARD lengthscale", unit="m", gt=0.0)
    noise_init: float = opt(
        0.02, "initial likelihood noise variance, in squared units of the scaled target", gt=0.0
    )
    natural_gradient: bool = opt(True, "streaming: NGD on q(u) plus Adam on the rest")
    ngd_lr: float = opt(0.1, "natural-gradient step size", gt=0.0, le=1.0)
    adam_lr: float = opt(0.01, "Adam rate for kernel and likelihood hyperparameters", gt=0.0)
    inducing_lr: float = opt(1e-3, "Adam rate for the inducing locations", ge=0.0)
    steps_per_update: int = opt(4, "streaming: optimisation steps per update call", ge=1)
    replay_fraction: float = opt(
        1.0,
        "streaming: share of each minibatch drawn from the whole store (rest: newest points)",
        ge=0.0,
        le=1.0,
    )
    ready_min_steps: int = opt(
        30, "streaming: model is ready after this many steps since it was created", ge=0
    )
    ready_max_moved_fraction: float = opt(
        0.15,
        "streaming: and at most this share of the inducing points moved within the last "
        "ready_move_window steps",
        ge=0.0,
        le=1.0,
    )
    ready_move_window: int = opt(
        4, "streaming: steps over which inducing-point moves count against readiness", ge=1, le=100_000
    )
    ready_elbo_slope: float = opt(
        0.05,
        "streaming: and the minibatch ELBO changes by less than this per point and per step "
        "(mean of the last ready_elbo_window steps against the window before)",
        unit="nats",
        gt=0.0,
    )
    ready_elbo_window: int = opt(
        10, "streaming: steps in each of the two windows that ready_elbo_slope compares", ge=1, le=100_000
    )
    inducing_policy: str = opt(
        "spread",
        "streaming: how inducing points follow new views: 'spread' keeps them spread like a "
        "farthest-point sample of all points (moving the most crowded), 'coverage' moves the "
        "least influential ones only where new points are coverage_lengthscales away",
        choices=("spread", "coverage"),
    )
    spread_factor: float = opt(
        1.0,
        "spread: new points farther than this many inducing spacings (median nearest-neighbour "
        "distance) from every inducing point get one",
        gt=0.0,
    )
    coverage_lengthscales: float = opt(
        1.5,
        "coverage: new points farther than this many lengthscales from all inducing points trigger a move",
        gt=0.0,
    )
    predict_chunk: int = opt(20000, "points per batched prediction call on the CPU", ge=256, le=10_000_000)
    predict_chunk_cuda: int = opt(
        65536,
        "points per batched prediction call on CUDA (larger than on the CPU: each call's kernel "
        "launches cost the same whatever its size, so fewer, larger calls are faster)",
        ge=256,
        le=10_000_000,
    )
    output_units: str = opt(
        "density",
        "units of mu and sigma^2 before Eq. 8: density (mapped back: mu s, sigma^2 s^2) or the "
        "normalised training units",
        choices=("density", "normalised"),
    )

    def __post_init__(self) -> None:
        _check(
            self.num_inducing == 0 or self.num_inducing >= 8,
            f"num_inducing: 0 (auto) or at least 8, got {self.num_inducing}",
        )


@dataclass(frozen=True, slots=True)
class CubatureConfig:
    """Sigma points (Eq. 9-12) and Algorithm 1."""

    alpha: float = opt(1.0, "unscented alpha (1,0,0 = spherical-radial cubature)", gt=0.0)
    beta: float = opt(0.0, "unscented beta", ge=0.0)
    kappa: float = opt(0.0, "unscented kappa", ge=-2.9)
    variance_form: str = opt(
        "paper_literal",
        "sigma^2_occ: paper_literal = sum w sigma2_pred (A); total = law of total variance (B), "
        "whose spread term peaks where the density is highest, so it penalises the densely "
        "observed surface rather than the torn edge",
        choices=("total", "paper_literal"),
    )
    max_query_points: int = opt(
        5000, "random subsample cap on the query cloud given to Algorithm 1", ge=100, le=1_000_000
    )


@dataclass(frozen=True, slots=True)
class ReconstructionConfig:
    """The fused cloud that grasps are scored on: TSDF fusion, mesh sampling, outlier removal."""

    tsdf_voxel_m: float = opt(0.003, "TSDF voxel size (paper: 3 mm)", unit="m", gt=0.0)
    sdf_trunc_voxels: float = opt(4.0, "TSDF truncation distance in voxels", gt=0.0)
    block_count: int = opt(
        40000,
        "VoxelBlockGrid block capacity (8^3 voxels, about 10 kB each, allocated at start); beyond "
        "it the blocks observed longest ago are evicted, so the grid never grows with the "
        "explored space",
        ge=100,
        le=400_000,
    )
    sample_points: int = opt(8000, "points sampled from the fused surface", ge=100, le=10_000_000)
    outlier_nb_neighbors: int = opt(20, "statistical outlier removal neighbourhood", ge=1, le=1000)
    outlier_std_ratio: float = opt(
        0.01, "statistical outlier removal std ratio (paper: 0.01; 0.1 less aggressive)", gt=0.0
    )
    outlier_removal: bool = opt(True, "apply statistical outlier removal")


@dataclass(frozen=True, slots=True)
class GripperConfig:
    """Parallel-jaw gripper geometry; defaults approximate the Reach Bravo 7 jaws."""

    max_width_m: float = opt(0.10, "maximum jaw opening", unit="m", gt=0.0)
    min_width_m: float = opt(0.005, "narrowest graspable width", unit="m", ge=0.0)
    depth_m: float = opt(0.09, "wrist origin to finger-pad line along the approach", unit="m", gt=0.0)
    finger_length_m: float = opt(0.045, "finger length along the approach", unit="m", gt=0.0)
    finger_width_m: float = opt(0.02, "finger extent along the jaw-plane normal", unit="m", gt=0.0)
    finger_thickness_m: float = opt(0.012, "finger thickness along the closing axis", unit="m", gt=0.0)
    palm_depth_m: float = opt(0.03, "palm block depth behind the fingers", unit="m", gt=0.0)
    palm_width_m: float = opt(0.06, "palm extent along the jaw-plane normal", unit="m", gt=0.0)


@dataclass(frozen=True, slots=True)
class FreeSpaceConfig:
    """What the depth maps say about space around the object: seen free, surface, or unknown
    (``pugsd.core.freespace``); the swept-volume uncertainty of a grasp reads it."""

    enabled: bool = opt(True, "keep the free-space map (grasp.uncertainty = swept needs it)")
    voxel_m: float = opt(0.015, "voxel edge", unit="m", gt=0.0, le=1.0)
    margin_m: float = opt(
        0.01,
        "a voxel centre within this of the measured depth is on the surface; nearer is seen free",
        unit="m",
        ge=0.0,
        le=1.0,
    )
    extent_m: float = opt(
        0.35,
        "how far around each frame's observed surface space is tracked (at least the grasp's "
        "approach stand-off plus the gripper's depth)",
        unit="m",
        gt=0.0,
        le=5.0,
    )
    background_range_m: float = opt(
        1.0,
        "a pixel the frame's mask marks as background has its ray free this far (0: masks say "
        "nothing about free space)",
        unit="m",
        ge=0.0,
        le=100.0,
    )
    max_blocks: int = opt(
        20000,
        "blocks (8^3 voxels, 2 KiB each) kept; the least recently updated are evicted beyond",
        ge=1,
        le=10_000_000,
    )


@dataclass(frozen=True, slots=True)
class GraspConfig:
    """Grasp proposal, Eq. 13 reweighting, ranking and thinning."""

    proposer: str = opt(
        "single_contact",
        "grasp proposer: single_contact (a contact on the observed surface, approach and roll "
        "enumerated, the far finger allowed where nothing was observed), antipodal (both contacts "
        "observed) or torchscript (a user's network)",
        choices=("single_contact", "antipodal", "torchscript"),
    )
    model_path: str = opt("", "TorchScript model file for proposer = torchscript")
    uncertainty: str = opt(
        "swept",
        "sigma^2 of a grasp in Eq. 13: swept (sigma^2_occ at the contact over the SVGP's prior "
        "variance, plus unknown_weight times the share of the gripper's swept volume never "
        "observed; unit-free) or contact (the paper's sigma^2_occ at the contact, density units)",
        choices=("swept", "contact"),
    )
    gamma: float = opt(
        1.0,
        "Eq. 13 weight gamma: GS / (1 + gamma sigma^2) (paper: 5, on its contact-point sigma^2 in "
        "density units; chosen on tuning seeds for the unit-free swept sigma^2)",
        ge=0.0,
        le=1e12,
    )
    unknown_weight: float = opt(
        20.0,
        "grasp.uncertainty = swept: weight of the never-observed share of the swept volume",
        ge=0.0,
        le=1e6,
    )
    unknown_decay_m: float = opt(
        0.02,
        "grasp.uncertainty = swept: a swept sample's never-observed space counts by exp(-d / this), "
        "d its distance to the observed cloud (unknown space far from everything seen is likely "
        "empty)",
        unit="m",
        gt=0.0,
        le=10.0,
    )
    swept_step_m: float = opt(
        0.02,
        "spacing of the swept-volume samples along the approach (and within the gripper)",
        unit="m",
        gt=0.0,
        le=0.5,
    )
    threads: int = opt(
        2,
        "threads for the single-contact proposal's contacts and the swept-volume distances "
        "(the same grasps for any number; 1: the calling thread only)",
        ge=1,
        le=64,
    )
    single_contact_max_contacts: int = opt(
        150, "single_contact: contacts sampled (farthest point) per proposal", ge=1, le=100_000
    )
    single_contact_face_deg: float = opt(
        45.0,
        "single_contact: a jaw's face counts as observed where its points' mean normal lies "
        "within this angle of the closing direction",
        unit="deg",
        gt=0.0,
        lt=90.0,
    )
    single_contact_voxel_m: float = opt(
        0.004,
        "single_contact: the cloud is thinned to one point per voxel of this edge for the jaw "
        "placement and collision tests (the contacts and normals come from the whole cloud)",
        unit="m",
        ge=0.0,
        le=0.05,
    )
    single_contact_approaches: int = opt(
        7,
        "single_contact: approach directions per contact, from along the outward normal "
        "(inwards) to tangent on either side, about the principal-curvature axis",
        ge=1,
        le=64,
    )
    single_contact_rolls: int = opt(
        4, "single_contact: closing directions (rolls about the approach) per approach", ge=1, le=64
    )
    top_k: int = opt(10, "grasps kept after ranking", ge=1, le=10_000)
    thin_distance_m: float = opt(
        0.01, "farthest-point thinning: minimum distance between kept grasps", unit="m", ge=0.0
    )
    normal_radius_m: float = opt(0.01, "PCA normal radius", unit="m", gt=0.0)
    friction_cone_deg: float = opt(25.0, "antipodal friction cone half-angle", unit="deg", gt=0.0, lt=90.0)
    num_orientations: int = opt(8, "approach orientations tried per contact pair", ge=1, le=360)
    max_contacts: int = opt(1500, "contacts sampled (farthest point) per proposal", ge=10, le=1_000_000)
    min_support: int = opt(6, "points required in the closing region", ge=1)
    partner_radius_m: float = opt(0.004, "radius of the partner search cylinder", unit="m", gt=0.0)
    clearance_m: float = opt(
        0.005,
        "margin kept between the observed cloud and the open fingers, the palm and its approach "
        "(a box cutting into a sampled surface can hold no sample: about the cloud's spacing plus "
        "its depth error)",
        unit="m",
        ge=0.0,
    )
    approach_check_m: float = opt(
        0.2,
        "straight approach checked behind the palm: the palm's cross-section swept this far back "
        "along the approach must be free (the arm's pre-grasp stand-off, arm.motion)",
        unit="m",
        ge=0.0,
    )
    gripper: GripperConfig = dataclasses.field(default_factory=GripperConfig)


@dataclass(frozen=True, slots=True)
class CoreConfig:
    """Aggregate of the core sections, handed to PugsPipeline."""

    stereo: StereoConfig = dataclasses.field(default_factory=StereoConfig)
    observation: ObservationConfig = dataclasses.field(default_factory=ObservationConfig)
    fof: FofConfig = dataclasses.field(default_factory=FofConfig)
    svgp: SvgpConfig = dataclasses.field(default_factory=SvgpConfig)
    cubature: CubatureConfig = dataclasses.field(default_factory=CubatureConfig)
    reconstruction: ReconstructionConfig = dataclasses.field(default_factory=ReconstructionConfig)
    freespace: FreeSpaceConfig = dataclasses.field(default_factory=FreeSpaceConfig)
    grasp: GraspConfig = dataclasses.field(default_factory=GraspConfig)
