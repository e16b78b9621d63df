"""Settings of the FastSLAM core (a frozen dataclass: the core has no I/O; the
service's pydantic-settings class :class:`schemas.config.CentralSettings` and
``RunOptions.extra`` both map onto it)."""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

ASSOCIATIONS = ("known", "nn", "mht")
PROPOSALS = ("fastslam1", "fastslam2")


@dataclass(frozen=True)
class FastSlamConfig:
    """Every knob of :class:`~central.fastslam.filter.FastSlam`, with the reason for its default."""

    particles: int = 100
    association: str = "nn"  # known (ids given) | nn (max likelihood, gated) | mht (paper 001's n+2 split)
    seed: int = 0
    proposal: str = "fastslam1"  # fastslam1: sample from the motion model; fastslam2: fold the scan into the proposal
    gate_probability: float = 0.99  # χ²(2) gate for association: 9.21 (DESIGN §4)
    new_landmark_probability: float = 0.999  # nn: outside this χ²(2) region of every landmark a detection is new (13.8)
    exclusive: bool = True  # one detection per landmark per scan (paper 001's NN does not assume it: set False for it)
    mht_prune: float = 0.3  # mht: drop a child whose weight is below this fraction of its parent's best child
    mht_max_factor: float = 4.0  # mht: resample back to N as soon as the split set exceeds this many times N
    new_landmark_rate: float = 0.5  # mht: expected new landmarks per scan (λ_n), against the sensor's clutter rate (λ_c)
    clutter_rate: float | None = None  # mht: false detections per scan (λ_c); None: the sensor's clutter_rate
    resample_ess: float = 0.5  # resample (systematic) when the effective sample size falls below this fraction
    motion_noise_scale: float = 1.0  # multiplies the control covariance of every odometry message
    pose_noise_per_s: tuple[float, float, float] = (0.0, 0.0, 0.0)  # extra σ (m, m, rad) per √s: slip, unmodelled
    sensor_noise_scale: float = 1.0  # multiplies the scan's noise covariance
    max_batch_s: float = 1.0  # integrate buffered controls at least this often (keeps the linearisation small)
    max_extrapolation_s: float = 0.2  # extend the last control to a scan stamp (or over an odometry gap) by at most this
    exist_init: float = 1.0  # landmark existence (log-odds-like score): value at creation
    exist_hit: float = 1.0  # added when the landmark is associated
    exist_miss: float = 1.0  # a miss adds exist_miss · ln(1 − P_D·v) (v: visibility), the log-odds of a missed detection
    exist_min: float = 0.0  # below this the landmark is deleted
    exist_max: float = 6.0  # upper clamp (a long-known landmark survives a run of misses)
    permanent_hits: int | None = 5  # a landmark associated this many times is never deleted (None: any may die)
    merge_duplicates: bool = True  # delete a confirmed landmark statistically identical to one just associated
    confirm_hits: int = 3  # a landmark appears in the published map once associated this many times
    miss_weight: bool = True  # weight particles by (1 − P_D) per landmark in view and not detected (kills duplicates)
    detection_probability: float | None = None  # P_D of a landmark in view; None: the sensor's (RobotInfo)
    max_detection_probability: float = 0.95  # P_D is capped here (a miss never costs log 0)
    max_obs_range: float | None = None  # ignore detections farther than this (m); None: the sensor's max range
    robot_detections: bool = False  # weight particles by robot-to-robot detections (relative pose likelihood)
    robot_detection_max_dt: float = 0.1  # ... only when the other robot's pose is this recent (s)

    def __post_init__(self) -> None:
        if self.particles < 1:
            raise ValueError("particles must be at least 1")
        if self.association not in ASSOCIATIONS:
            raise ValueError(f"association must be one of {ASSOCIATIONS}, not {self.association!r}")
        if self.proposal not in PROPOSALS:
            raise ValueError(f"proposal must be one of {PROPOSALS}, not {self.proposal!r}")
        for name in ("gate_probability", "new_landmark_probability"):
            if not 0.0 < getattr(self, name) < 1.0:
                raise ValueError(f"{name} must be in (0, 1)")
        if self.new_landmark_probability < self.gate_probability:
            raise ValueError("new_landmark_probability must be at least gate_probability")
        if self.new_landmark_rate <= 0 or (self.clutter_rate is not None and self.clutter_rate < 0):
            raise ValueError("new_landmark_rate must be positive and clutter_rate non-negative")
        if not 0.0 < self.mht_prune <= 1.0 or self.mht_max_factor < 1.0:
            raise ValueError("mht_prune must be in (0, 1] and mht_max_factor at least 1")
        if not 0.0 <= self.resample_ess <= 1.0:
            raise ValueError("resample_ess must be in [0, 1]")
        if self.motion_noise_scale <= 0 or self.sensor_noise_scale <= 0 or self.max_batch_s <= 0:
            raise ValueError("noise scales and max_batch_s must be positive")
        if len(self.pose_noise_per_s) != 3 or min(self.pose_noise_per_s) < 0:
            raise ValueError("pose_noise_per_s is three non-negative standard deviations")
        if self.exist_hit <= 0 or self.exist_miss < 0 or self.exist_init <= self.exist_min or self.exist_max < self.exist_init:
            raise ValueError("existence: need hit > 0, miss >= 0, min < init <= max")

    def with_overrides(self, overrides: dict) -> "FastSlamConfig":
        """A copy with ``overrides`` (unknown names raise ValueError)."""
        names = {f.name for f in fields(self)}
        unknown = sorted(set(overrides) - names)
        if unknown:
            raise ValueError(f"unknown FastSLAM settings: {', '.join(unknown)}")
        values = dict(overrides)
        if "pose_noise_per_s" in values:
            values["pose_noise_per_s"] = tuple(float(v) for v in values["pose_noise_per_s"])
        return replace(self, **values)
