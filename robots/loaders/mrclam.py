"""UTIAS MR.CLAM (Leung et al., IJRR 2011): five robots, fifteen barcoded landmarks, Vicon truth.

Files (see ``utias_mrclam/SOURCE.md``), plain ``.dat`` or ``.dat.xz``:
``Barcodes`` (subject, barcode), ``Landmark_Groundtruth`` (subject, x, y, σx, σy),
``RobotN_Odometry`` (t, v, ω) at ≈ 100 Hz, ``RobotN_Measurement`` (t, barcode,
range, bearing), ``RobotN_Groundtruth`` (t, x, y, θ).

Column 2 of the measurements is a *barcode*: it is mapped to a subject through
Barcodes.dat. Subjects 1-5 are robots (kept as robot-to-robot detections of
``r1`` … ``r5``), 6-20 landmarks (their subject number is the landmark id);
barcodes not in the table are dropped and counted in ``Dataset.meta``. Each
robot starts at its Vicon pose at its first odometry stamp. Stamps stay in
the data set's Unix seconds, shared by all robots; ``meta["fleet_start"]`` is the
first odometry stamp of any robot of the folder (also when one robot is loaded),
so separate replay processes can share one clock origin.

Default noise: fitted to Dataset 6 residuals against Vicon (robust spread,
rounded up): σ_range 0.15 m, σ_bearing 0.025 rad; odometry σ_v 0.02 m/s,
σ_ω 0.10 rad/s per ≈ 10 ms reading.

The odometry's heading error is not white: it grows with the angle turned (wheel slip). Over 4 s windows of
the five robots, σ_ω alone leaves 28 % of the windows with more than 0.5 rad turned outside 3σ. Each robot
announces it as ``RobotInfo.turn_slip_var`` (``turn_slip_var``, rad² of heading variance per radian turned;
0.013-0.015 fits Dataset 6 over 1-30 s windows, 0.015 by default): with it every window is within 3σ.
Estimators choose whether to model it (D-SLAM does by default, FastSLAM does not: docs/dslam.md and
docs/fastslam.md).

The camera misses most landmarks it could see: of the landmarks inside its view (0.3 m and 0.05 rad within its
limits) at a scan's Vicon pose, 23-32 % per robot are detected in that scan, 30 % over Dataset 6's five robots
(about half within 2 m, a sixth beyond 6 m; the barcodes of a cluster stand 0.2 m apart and one often hides
another). The sensor announces it as ``SensorSpec.detection_probability`` (``detection_probability``, 0.3): a
pose that puts an undetected landmark in view is then hardly less likely than one that does not, which is what
the data says.

Dataset 1's survey disagrees with its detections about landmarks 11 and 17 (barcodes 18 and 61). Mapped with
barcodes and no start poses, and fitted to the survey by id, each lands within 0.1 m of the *other's* surveyed
position; the other thirteen land within 0.18 m of their own. FastSLAM and D-SLAM agree on this. The loader keeps
the files as they are, so score Dataset 1's maps with the two swapped.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from robots.dataset import Dataset, RobotLog
from robots.loaders.common import (
    find_file, first_stamp, group_by_stamp, median_rate, odometry_intervals, offsets_at, read_table,
)
from schemas.messages import RobotInfo, SensorSpec

ROBOT_SUBJECTS = range(1, 6)


def robot_id(subject: int) -> str:
    return f"r{subject}"


def _barcode_table(folder: Path) -> dict[int, int]:
    table = read_table(find_file(folder, "Barcodes.dat"), 2)
    return {int(barcode): int(subject) for subject, barcode in table}


def _has_file(folder: Path, name: str) -> bool:
    try:
        find_file(folder, name)
    except FileNotFoundError:
        return False
    return True


def load_mrclam(
    folder: str | Path,
    robots: list[int] | None = None,
    range_std: float = 0.15,
    bearing_std: float = 0.025,
    v_std: float = 0.02,
    w_std: float = 0.10,
    turn_slip_var: float = 0.015,
    detection_probability: float = 0.3,
    max_range: float = 9.5,
    fov: float = 1.25,
) -> Dataset:
    """Load a MR.CLAM data set folder; ``robots`` (subjects 1-5) selects robots (default: every robot with odometry);
    ``turn_slip_var`` is the robots' heading variance per radian turned, ``detection_probability`` the share of the
    landmarks in view the camera detects (see the module docstring)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"MR.CLAM folder {folder} does not exist")
    for subject in robots or []:
        if subject not in ROBOT_SUBJECTS:
            raise ValueError(f"MR.CLAM robot {subject} does not exist (robots are 1-5)")
    subjects = list(robots) if robots else [s for s in ROBOT_SUBJECTS if _has_file(folder, f"Robot{s}_Odometry.dat")]
    if not subjects:
        raise FileNotFoundError(f"no RobotN_Odometry.dat[.xz] in {folder}")
    barcodes = _barcode_table(folder)
    landmark_table = read_table(find_file(folder, "Landmark_Groundtruth.dat"), 5)
    landmark_ids = landmark_table[:, 0].astype(np.int64)
    sensor = SensorSpec(min_range=0.0, max_range=max_range, fov=fov,
                        noise_cov=np.diag([range_std**2, bearing_std**2]), detection_probability=detection_probability)
    logs: dict[str, RobotLog] = {}
    starts = [first_stamp(find_file(folder, f"Robot{s}_Odometry.dat")) for s in ROBOT_SUBJECTS
              if _has_file(folder, f"Robot{s}_Odometry.dat")]
    meta: dict = {"folder": str(folder), "fleet_start": min(t for t in starts if t is not None), "unknown_barcodes": {}, "landmark_detections": {}, "robot_detections": {},
                  "odometry_rows": {}, "odometry_duplicates": {}, "truth_rows": {}}
    for subject in subjects:
        rid = robot_id(subject)
        odometry = read_table(find_file(folder, f"Robot{subject}_Odometry.dat"), 3)
        measurements = read_table(find_file(folder, f"Robot{subject}_Measurement.dat"), 4)
        truth = (read_table(find_file(folder, f"Robot{subject}_Groundtruth.dat"), 4)
                 if _has_file(folder, f"Robot{subject}_Groundtruth.dat") else np.zeros((0, 4)))
        stamps, dt, controls, duplicates = odometry_intervals(odometry[:, 0], odometry[:, 1:3])

        measurements = measurements[np.argsort(measurements[:, 0], kind="stable")]
        seen = np.array([barcodes.get(int(b), -1) for b in measurements[:, 1]], np.int64)
        is_robot = np.isin(seen, list(ROBOT_SUBJECTS))
        is_landmark = np.isin(seen, landmark_ids)
        known = is_robot | is_landmark
        scan_stamp, _ = group_by_stamp(measurements[known, 0])
        landmarks_seen = measurements[is_landmark]
        robots_seen = measurements[is_robot]

        info = RobotInfo(
            robot_id=rid, stamp=float(odometry[0, 0]), motion_model="unicycle", sensor=sensor,
            source=f"replay:mrclam:{folder.name}", odom_rate_hz=median_rate(odometry[:, 0]),
            scan_rate_hz=max(scan_stamp.size / max(np.ptp(scan_stamp), 1.0), 1e-3) if scan_stamp.size else 1.0,
            turn_slip_var=turn_slip_var,
        )
        odom_cov = np.diag([v_std**2, w_std**2])
        log = RobotLog(
            info=info, odom_stamp=stamps, odom_dt=dt, odom_control=controls, odom_cov=odom_cov,
            scan_stamp=scan_stamp, scan_offsets=offsets_at(landmarks_seen[:, 0], scan_stamp),
            det_range=landmarks_seen[:, 2].copy(), det_bearing=landmarks_seen[:, 3].copy(),
            det_id=seen[is_landmark], scan_cov=sensor.noise_cov,
            truth_stamp=truth[:, 0].copy(), truth_pose=truth[:, 1:4].copy(),
            robot_det_offsets=offsets_at(robots_seen[:, 0], scan_stamp),
            robot_det_ids=[robot_id(s) for s in seen[is_robot].tolist()],
            robot_det_range=robots_seen[:, 2].copy(), robot_det_bearing=robots_seen[:, 3].copy(),
        )
        if truth.shape[0]:
            start = log.truth_at(np.array([odometry[0, 0]]))[0]
            if np.all(np.isfinite(start)):
                log.info = info.model_copy(update={"start_pose": start, "start_pose_cov": np.diag([1e-6, 1e-6, 1e-6])})
        logs[rid] = log
        meta["unknown_barcodes"][rid] = int((~known).sum())
        meta["landmark_detections"][rid] = int(is_landmark.sum())
        meta["robot_detections"][rid] = int(is_robot.sum())
        meta["odometry_rows"][rid] = int(odometry.shape[0])
        meta["odometry_duplicates"][rid] = duplicates
        meta["truth_rows"][rid] = int(truth.shape[0])
    return Dataset(name=f"mrclam:{folder.name}", robots=logs, landmarks=landmark_table[:, 1:3].copy(),
                   landmark_ids=landmark_ids, meta=meta)
