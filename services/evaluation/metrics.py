"""How good is an estimate? Trajectory, map, association, consistency and timing metrics (pure numpy/scipy).

- ATE: RMSE of position errors, raw and after the SE(2) alignment (Horn/Umeyama
  in the plane, no scale: :func:`robots.models.fit_se2`) that best lays the
  estimate on the truth.
- RPE: error of the relative motion over a fixed time step (translation, rotation).
- Map error: estimated ↔ true landmarks matched by ``linear_sum_assignment`` on
  distances; pairs farther than a cut-off are no match. RMSE of the matches,
  missed true landmarks, spurious estimated ones.
- Association accuracy, where truth ids exist.
- NEES with chi-square bounds (consistency of the reported covariance).
- Timing: median and p99.

Trajectories are compared at the estimate's stamps with the truth interpolated
there (truth is dense: simulator, Vicon), except that GPS-like truth without
heading is also compared at its own fixes (``gps_rmse_m``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.stats import chi2

from robots.models import fit_se2, se2_between, transform_points, wrap_angle


@dataclass
class Trajectory:
    """Time-stamped poses ``(n, 3)`` (θ may be NaN: position-only truth), optional covariances ``(n, 3, 3)``."""

    stamps: np.ndarray
    poses: np.ndarray
    covs: np.ndarray | None = None

    @classmethod
    def from_lists(cls, stamps: list[float], poses: list, covs: list | None = None) -> "Trajectory":
        poses_array = np.asarray(poses, float).reshape(-1, 3)
        covs_array = None if covs is None or len(covs) != len(poses) else np.asarray(covs, float).reshape(-1, 3, 3)
        return cls(np.asarray(stamps, float), poses_array, covs_array)

    def __len__(self) -> int:
        return int(self.stamps.shape[0])

    @property
    def has_heading(self) -> bool:
        return bool(len(self)) and bool(np.all(np.isfinite(self.poses[:, 2])))


def interpolate_poses(stamps: np.ndarray, poses: np.ndarray, at: np.ndarray, max_gap: float | None = None) -> np.ndarray:
    """Poses at times ``at`` by linear interpolation (θ unwrapped first); NaN outside the span or across a gap.

    ``max_gap``: no value where the two bracketing samples are more than this apart.
    """
    at = np.asarray(at, float)
    out = np.full(at.shape + (3,), np.nan)
    if stamps.shape[0] == 0:
        return out
    inside = (at >= stamps[0]) & (at <= stamps[-1])
    if max_gap is not None and stamps.shape[0] > 1:
        right = np.clip(np.searchsorted(stamps, at, side="left"), 1, stamps.shape[0] - 1)
        exact = stamps[np.clip(np.searchsorted(stamps, at), 0, stamps.shape[0] - 1)] == at
        inside &= exact | (stamps[right] - stamps[right - 1] <= max_gap)
    for j in range(2):
        out[inside, j] = np.interp(at[inside], stamps, poses[:, j])
    heading = poses[:, 2]
    if np.all(np.isfinite(heading)):
        out[inside, 2] = wrap_angle(np.interp(at[inside], stamps, np.unwrap(heading)))
    return out


def pose_errors(estimated: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Errors estimated − truth ``(n, 3)`` with the heading difference wrapped."""
    error = np.asarray(estimated, float) - np.asarray(truth, float)
    error[..., 2] = wrap_angle(error[..., 2])
    return error


def rmse(values: np.ndarray) -> float | None:
    """Root mean square of the norms of ``values`` (rows), None when empty."""
    values = np.asarray(values, float)
    if values.size == 0:
        return None
    squared = values**2 if values.ndim == 1 else np.sum(values**2, axis=-1)
    return float(np.sqrt(np.mean(squared)))


def ate(estimated_xy: np.ndarray, truth_xy: np.ndarray, align: bool = False) -> dict:
    """Absolute trajectory error of matched positions ``(n, 2)``, raw or after the best SE(2) alignment."""
    estimated_xy, truth_xy = np.asarray(estimated_xy, float), np.asarray(truth_xy, float)
    alignment = np.zeros(3)
    if align and estimated_xy.shape[0] >= 2:
        alignment = fit_se2(estimated_xy, truth_xy)
        estimated_xy = transform_points(alignment, estimated_xy)
    distance = np.linalg.norm(estimated_xy - truth_xy, axis=-1)
    return {
        "rmse_m": rmse(distance),
        "mean_m": float(distance.mean()) if distance.size else None,
        "max_m": float(distance.max()) if distance.size else None,
        "points": int(distance.size),
        "alignment": [float(v) for v in alignment],
    }


def rpe(stamps: np.ndarray, estimated: np.ndarray, truth: np.ndarray, delta_s: float) -> dict:
    """Relative pose error over ``delta_s``: for each sample i and the first j with t_j ≥ t_i + delta_s,
    E = (T_true,i⁻¹ T_true,j)⁻¹ (T_est,i⁻¹ T_est,j); RMSE of its translation and rotation."""
    stamps = np.asarray(stamps, float)
    j = np.searchsorted(stamps, stamps + delta_s, side="left")
    i = np.flatnonzero(j < stamps.shape[0])
    j = j[i]
    if i.size == 0:
        return {"delta_s": delta_s, "pairs": 0, "translation_rmse_m": None, "rotation_rmse_rad": None}
    error = se2_between(se2_between(truth[i], truth[j]), se2_between(estimated[i], estimated[j]))
    return {
        "delta_s": delta_s,
        "pairs": int(i.size),
        "translation_rmse_m": rmse(error[:, :2]),
        "rotation_rmse_rad": rmse(error[:, 2]),
    }


def nees(errors: np.ndarray, covs: np.ndarray) -> np.ndarray:
    """Normalised estimation error squared eᵀ P⁻¹ e of each row (NaN where P is singular)."""
    errors, covs = np.asarray(errors, float), np.asarray(covs, float)
    out = np.full(errors.shape[0], np.nan)
    if errors.shape[0] == 0:
        return out
    ok = np.linalg.det(covs) > 0
    if np.any(ok):
        solved = np.linalg.solve(covs[ok], errors[ok][..., None])[..., 0]
        out[ok] = np.sum(errors[ok] * solved, axis=-1)
    return out


def nees_summary(values: np.ndarray, dof: int, probability: float = 0.95) -> dict:
    """Mean NEES and its two-sided chi-square bounds for ``n`` samples of ``dof`` degrees of freedom.

    If the filter is consistent, n·mean ~ χ²(n·dof), so the mean lies within
    [χ²⁻¹((1−p)/2; n·dof)/n, χ²⁻¹((1+p)/2; n·dof)/n] with probability p. The
    samples of one trajectory are correlated, so this interval is optimistic;
    ``within`` is the fraction of single samples under χ²⁻¹(p; dof).
    """
    values = np.asarray(values, float)
    values = values[np.isfinite(values)]
    n = values.size
    if n == 0:
        return {"samples": 0, "dof": dof, "mean": None, "lower": None, "upper": None, "within": None, "consistent": None}
    lower = float(chi2.ppf((1 - probability) / 2, n * dof) / n)
    upper = float(chi2.ppf((1 + probability) / 2, n * dof) / n)
    mean = float(values.mean())
    return {
        "samples": int(n), "dof": dof, "mean": mean, "lower": lower, "upper": upper,
        "within": float(np.mean(values <= chi2.ppf(probability, dof))),
        "consistent": bool(lower <= mean <= upper),
    }


def map_error(estimated: np.ndarray, truth: np.ndarray, cutoff: float = 1.0) -> dict:
    """Match estimated ``(n, 2)`` to true ``(L, 2)`` landmarks (optimal assignment on distance, cut-off).

    Pairs farther than ``cutoff`` are not matches: costs above it are replaced
    by a value no assignment wants, and such pairs are dropped afterwards.
    """
    estimated = np.asarray(estimated, float).reshape(-1, 2)
    truth = np.asarray(truth, float).reshape(-1, 2)
    result = {"estimated": int(estimated.shape[0]), "true": int(truth.shape[0]), "matched": 0,
              "missed": int(truth.shape[0]), "spurious": int(estimated.shape[0]), "rmse_m": None, "cutoff_m": cutoff,
              "pairs": []}
    if estimated.shape[0] == 0 or truth.shape[0] == 0:
        return result
    distance = np.linalg.norm(estimated[:, None, :] - truth[None, :, :], axis=-1)
    penalty = cutoff * (1.0 + estimated.shape[0] + truth.shape[0])
    rows, cols = linear_sum_assignment(np.where(distance <= cutoff, distance, penalty))
    keep = distance[rows, cols] <= cutoff
    rows, cols = rows[keep], cols[keep]
    result.update(matched=int(rows.size), missed=int(truth.shape[0] - rows.size),
                  spurious=int(estimated.shape[0] - rows.size), rmse_m=rmse(distance[rows, cols]),
                  pairs=[[int(r), int(c)] for r, c in zip(rows, cols)])
    return result


def map_alignment(estimated: np.ndarray, truth: np.ndarray, cutoff: float = 1.0, inlier: float = 0.3,
                  max_landmarks: int = 100) -> dict:
    """The map's errors after one SE(2) transform fitted from the map alone, for runs with a survey but no robot
    truth whose frame is an anchor robot's (MR.CLAM Dataset 1 without start poses). Landmarks carry no usable
    ids here, so the fit registers point sets: every pair of mapped landmarks at least 0.5 m apart against
    every surveyed pair whose distance agrees within ``inlier``, keeping the transform that brings the most
    mapped landmarks within ``inlier`` of the survey, refined on them. Returns the transform (x, y, θ), the
    errors of :func:`map_error` after it and ``within_inlier`` (surveyed landmarks with a mapped one within
    ``inlier``); empty with fewer than two landmarks on either side, or more than ``max_landmarks`` mapped (the
    search grows with the square of the map: 4 s for 60 landmarks)."""
    estimated = np.asarray(estimated, float).reshape(-1, 2)
    truth = np.asarray(truth, float).reshape(-1, 2)
    if min(estimated.shape[0], truth.shape[0]) < 2 or estimated.shape[0] > max_landmarks:
        return {}
    def to_survey(transform: np.ndarray) -> np.ndarray:  # (mapped, surveyed) distances after ``transform``
        return np.linalg.norm(transform_points(transform, estimated)[:, None] - truth[None], axis=-1)

    true_gap = np.linalg.norm(truth[:, None] - truth[None], axis=-1)
    mapped_gap = np.linalg.norm(estimated[:, None] - estimated[None], axis=-1)
    best, transform = (-1, np.inf), None
    for i, j in zip(*np.nonzero(np.triu(mapped_gap >= 0.5, 1))):
        for p, q in zip(*np.nonzero(np.abs(true_gap - mapped_gap[i, j]) < inlier)):
            candidate = fit_se2(estimated[[i, j]], truth[[p, q]])
            nearest = to_survey(candidate).min(1)
            close = nearest < inlier
            score = (int(close.sum()), float(np.sum(nearest[close] ** 2)))
            if score[0] > best[0] or (score[0] == best[0] and score[1] < best[1]):
                best, transform = score, candidate
    if transform is None:
        return {}
    for _ in range(3):
        distance = to_survey(transform)
        close = distance.min(1) < inlier
        if close.sum() < 2:
            break
        transform = fit_se2(estimated[close], truth[distance[close].argmin(1)])
    detail = map_error(transform_points(transform, estimated), truth, cutoff)
    within = int((to_survey(transform).min(0) <= inlier).sum())
    return {"transform": np.asarray(transform).tolist(), "map_rmse_m": detail["rmse_m"], "within_inlier": within,
            "inlier_m": inlier, "landmarks": {k: detail[k] for k in ("estimated", "matched", "missed", "spurious")}}


def association_accuracy(true_ids: np.ndarray, estimated_labels: np.ndarray) -> dict:
    """Fraction of detections associated correctly, where truth ids exist.

    ``true_ids``: the true landmark of each detection (−1: clutter).
    ``estimated_labels``: the estimator's landmark label for it (−1: rejected as clutter).
    Labels are arbitrary, so each label stands for the true landmark most of its
    detections belong to (majority vote); a detection is correct when its label
    stands for its true landmark, or when clutter is rejected.
    """
    true_ids = np.asarray(true_ids, np.int64)
    labels = np.asarray(estimated_labels, np.int64)
    total = int(true_ids.size)
    if total == 0:
        return {"detections": 0, "correct": 0, "accuracy": None, "labels": 0}
    assigned = labels >= 0
    meaning = np.full(labels.shape, -2, np.int64)
    if np.any(assigned):
        pairs, counts = np.unique(np.stack([labels[assigned], true_ids[assigned]], -1), axis=0, return_counts=True)
        order = np.lexsort((-counts, pairs[:, 0]))
        pairs = pairs[order]
        first = np.r_[True, pairs[1:, 0] != pairs[:-1, 0]]
        majority = dict(zip(pairs[first, 0].tolist(), pairs[first, 1].tolist()))
        meaning[assigned] = [majority[v] for v in labels[assigned].tolist()]
    correct = np.where(assigned, meaning == true_ids, true_ids < 0)
    return {"detections": total, "correct": int(correct.sum()), "accuracy": float(correct.mean()),
            "labels": int(np.unique(labels[assigned]).size)}


def timing_stats(seconds: np.ndarray) -> dict:
    """Median, p99, mean and max of durations given in seconds, reported in milliseconds."""
    ms = np.asarray(seconds, float) * 1e3
    if ms.size == 0:
        return {"count": 0, "median_ms": None, "p99_ms": None, "mean_ms": None, "max_ms": None}
    return {"count": int(ms.size), "median_ms": float(np.median(ms)), "p99_ms": float(np.percentile(ms, 99)),
            "mean_ms": float(ms.mean()), "max_ms": float(ms.max())}


def trajectory_metrics(estimated: Trajectory, truth: Trajectory, truth_offset=(0.0, 0.0), rpe_delta_s: float = 1.0,
                       max_gap_s: float = 1.0) -> dict:
    """Every trajectory metric of one robot, and the per-sample errors for plots.

    ``truth_offset``: the body-frame point whose position the truth gives (a GPS
    antenna); the estimate is compared at that point. Heading, RPE and NEES
    need truth with heading at the body origin.
    """
    offset = np.asarray(truth_offset, float)
    body_truth = truth.has_heading and not np.any(offset)
    at_est = interpolate_poses(truth.stamps, truth.poses, estimated.stamps, max_gap_s)
    valid = np.all(np.isfinite(at_est[:, :2]), axis=-1)
    points = transform_points(estimated.poses, offset) if np.any(offset) else estimated.poses[:, :2]
    result: dict = {"samples": int(valid.sum()), "heading_known": bool(body_truth)}
    raw = ate(points[valid], at_est[valid, :2])
    aligned = ate(points[valid], at_est[valid, :2], align=True)
    result.update(ate_rmse_m=raw["rmse_m"], ate_max_m=raw["max_m"], ate_aligned_rmse_m=aligned["rmse_m"],
                  alignment=aligned["alignment"])
    error_xy = np.linalg.norm(points - at_est[:, :2], axis=-1)
    curves = {"stamps": estimated.stamps[valid], "position_error_m": error_xy[valid]}
    if body_truth:
        errors = pose_errors(estimated.poses[valid], at_est[valid])
        result["heading_rmse_rad"] = rmse(errors[:, 2])
        result["rpe"] = rpe(estimated.stamps[valid], estimated.poses[valid], at_est[valid], rpe_delta_s)
        curves["heading_error_rad"] = errors[:, 2]
        if estimated.covs is not None:
            values = nees(errors, estimated.covs[valid])
            result["nees"] = nees_summary(values, 3)
            curves["nees"] = values
    else:
        at_fixes = interpolate_poses(estimated.stamps, np.column_stack([points, np.zeros(len(points))]),
                                     truth.stamps, max_gap_s)
        fixes = np.all(np.isfinite(at_fixes[:, :2]), axis=-1)
        gps = ate(at_fixes[fixes, :2], truth.poses[fixes, :2], align=True)
        result["gps_rmse_m"] = gps["rmse_m"]
        result["gps_fixes"] = gps["points"]
    result["curves"] = curves
    return result


def score_estimates(trajectories: dict[str, dict[str, Trajectory]], truth: dict[str, Trajectory],
                    maps: dict[str, tuple[np.ndarray, np.ndarray | None]], true_landmarks: np.ndarray | None,
                    truth_offset=(0.0, 0.0), map_cutoff: float = 1.0, rpe_delta_s: float = 1.0,
                    max_gap_s: float = 1.0) -> tuple[dict, dict]:
    """Score every estimator's trajectories (per robot) and map against the truth.

    ``trajectories[estimator][robot]``, ``truth[robot]``, ``maps[estimator] = (means, covs)``
    (an estimator without an entry in ``maps`` has no map: its landmark figures are None).
    Returns (metrics, curves): metrics has a ``summary`` (per estimator: ATE per
    robot, map RMSE, landmark counts) and the full ``estimators`` detail;
    curves holds the per-sample errors for plots.
    """
    summary: dict = {}
    detail: dict = {}
    curves: dict = {}
    for name in sorted(set(trajectories) | set(maps)):
        robots: dict = {}
        curves[name] = {}
        for rid, estimated in sorted(trajectories.get(name, {}).items()):
            if rid not in truth or len(estimated) == 0:
                continue
            scored = trajectory_metrics(estimated, truth[rid], truth_offset, rpe_delta_s, max_gap_s)
            curves[name][rid] = scored.pop("curves")
            robots[rid] = scored
        entry: dict = {"ate_rmse_m": {r: m["ate_rmse_m"] for r, m in robots.items()},
                       "ate_aligned_rmse_m": {r: m["ate_aligned_rmse_m"] for r, m in robots.items()}}
        gps = {r: m["gps_rmse_m"] for r, m in robots.items() if "gps_rmse_m" in m}
        if gps:
            entry["gps_rmse_m"] = gps
        map_detail = None
        means = maps.get(name, (np.zeros((0, 2)), None))[0]
        if name not in maps:
            entry["map_rmse_m"] = None
            entry["landmarks"] = None
        elif true_landmarks is not None and len(true_landmarks):
            map_detail = map_error(means, true_landmarks, map_cutoff)
            entry["map_rmse_m"] = map_detail["rmse_m"]
            entry["landmarks"] = {k: map_detail[k] for k in ("estimated", "matched", "missed", "spurious")}
        else:
            entry["map_rmse_m"] = None
            entry["landmarks"] = {"estimated": int(len(means)), "matched": None, "missed": None, "spurious": None}
        summary[name] = entry
        detail[name] = {"robots": robots, "map": map_detail}
    return {"summary": summary, "estimators": detail}, curves


def fleet_alignment(trajectories: dict[str, Trajectory], truth: dict[str, Trajectory], max_gap_s: float = 1.0,
                    true_landmarks: np.ndarray | None = None, map_means: np.ndarray | None = None,
                    map_cutoff: float = 1.0, truth_offset=(0.0, 0.0)) -> dict:
    """Errors after one SE(2) transform for the whole fleet and its map, fitted to every robot's positions
    jointly (never one transform per robot, which would hide a robot placed in the wrong place).

    For runs whose world frame is not the truth's (robots placed without start poses). Returns the transform
    (x, y, θ), each robot's ATE after it and, with a true map, the map error after it; empty without samples.
    ``truth_offset``: the body-frame point the truth gives the position of (a GPS antenna).
    """
    offset = np.asarray(truth_offset, float)
    estimated, target, owner = [], [], []
    for rid, path in trajectories.items():
        if rid not in truth or len(path) == 0:
            continue
        at = interpolate_poses(truth[rid].stamps, truth[rid].poses, path.stamps, max_gap_s)
        valid = np.all(np.isfinite(at[:, :2]), axis=-1)
        estimated.append(transform_points(path.poses[valid], offset) if np.any(offset) else path.poses[valid, :2])
        target.append(at[valid, :2])
        owner += [rid] * int(valid.sum())
    if not owner:
        return {}
    source, goal, owner = np.concatenate(estimated), np.concatenate(target), np.array(owner)
    transform = fit_se2(source, goal)
    moved = transform_points(transform, source)
    error = np.linalg.norm(moved - goal, axis=-1)
    out = {"transform": transform.tolist(),
           "ate_rmse_m": {rid: rmse(error[owner == rid]) for rid in sorted(set(owner.tolist()))}}
    if true_landmarks is not None and len(true_landmarks) and map_means is not None:
        aligned = transform_points(transform, np.asarray(map_means, float).reshape(-1, 2)) if len(map_means) else map_means
        detail = map_error(aligned, true_landmarks, map_cutoff)
        out["map_rmse_m"] = detail["rmse_m"]
        out["landmarks"] = {k: detail[k] for k in ("estimated", "matched", "missed", "spurious")}
    return out
