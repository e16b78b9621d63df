"""Offline FastSLAM runs scored against the truth, for the benchmarks (``benchmarks/fastslam_*.py``).

One run goes through the offline runner (:func:`services.offline.run_estimator`,
the machinery of ``fleetslam run``) and is scored by
:func:`services.evaluation.metrics.score_estimates`: per-robot ATE against the
truth (raw and after SE(2) alignment, the error at GPS fixes where the truth
has no heading), and the map against the true landmarks.
"""

from __future__ import annotations

import time

import numpy as np

from robots.dataset import Dataset
from robots.models import fit_se2, transform_points
from schemas.contract import RunOptions
from services.evaluation.metrics import Trajectory, map_error, score_estimates
from services.offline import run_estimator


def run_and_score(dataset: Dataset, options: RunOptions, robots: list[str] | None = None,
                  duration: float | None = None, map_cutoff: float = 1.0) -> dict:
    """Run ``options`` over ``dataset`` (the chosen ``robots``, ``duration`` s of data) and score it."""
    chosen = robots or list(dataset.robots)
    cpu = time.process_time()
    result = run_estimator(dataset, options, chosen, duration)
    cpu = time.process_time() - cpu
    truth = {rid: Trajectory(dataset.robots[rid].truth_stamp, dataset.robots[rid].truth_pose)
             for rid in chosen if dataset.robots[rid].truth_stamp.size}
    metrics, _ = score_estimates({"run": result.trajectories}, truth, {"run": (result.map_means, result.map_covs)},
                                 dataset.landmarks, tuple(dataset.meta.get("truth_offset", (0.0, 0.0))), map_cutoff)
    summary = metrics["summary"]["run"]
    out = {
        "estimator": options.estimator, "association": options.association, "particles": options.particles,
        "settings": dict(options.settings), "robots": chosen,
        "wall_s": round(result.wall_s, 2), "cpu_s": round(cpu, 2), "data_s": round(result.data_s, 1),
        "ate_rmse_m": _rounded(summary["ate_rmse_m"]), "ate_aligned_rmse_m": _rounded(summary["ate_aligned_rmse_m"]),
        "landmarks_mapped": int(len(result.map_means)),
        "scan_ms_median": _ms(result.timing.get("scan", {}).get("median_ms")),
        "scan_ms_p99": _ms(result.timing.get("scan", {}).get("p99_ms")),
    }
    if "gps_rmse_m" in summary:
        out["gps_rmse_m"] = _rounded(summary["gps_rmse_m"])
    if dataset.landmarks is not None:
        out["map_rmse_m"] = None if summary["map_rmse_m"] is None else round(summary["map_rmse_m"], 3)
        out["landmarks"] = summary["landmarks"]
    out["map_means"] = result.map_means
    return out


def aligned_map_error(means: np.ndarray, truth: np.ndarray, anchors: np.ndarray | None = None,
                      cutoff: float = 1.0) -> tuple[dict, np.ndarray]:
    """Map error after the rigid 2-D transform that best fits matched landmarks (``anchors``: the true
    landmarks used for the fit, default all). SLAM fixes the map only up to such a transform when the start
    pose drifts; returns (map_error dict, aligned means)."""
    fit = truth if anchors is None else anchors
    if len(means) == 0:
        return map_error(means, truth, cutoff), means
    matched = map_error(means, fit, cutoff)["pairs"]
    if len(matched) < 2:
        return map_error(means, truth, cutoff), means
    transform = fit_se2(means[[r for r, _ in matched]], fit[[c for _, c in matched]])
    aligned = transform_points(transform, means)
    return map_error(aligned, truth, cutoff), aligned


def passed_beacons(dataset, means: np.ndarray, within: float = 0.3) -> dict:
    """Surveyed landmarks some robot's true track passes within sensor range of, how many of them the map
    holds within ``within`` m after the rigid fit of the map to the survey (the survey's frame is not the
    filter's), and the mapped landmarks farther than 1 m from every surveyed one after that fit (spurious in
    the frame the beacons are judged in); empty without a surveyed map or a track."""
    if dataset.landmarks is None or not len(means):
        return {}
    tracks = [log.truth_pose[np.all(np.isfinite(log.truth_pose[:, :2]), 1), :2] for log in dataset.robots.values()]
    reach = max(log.info.sensor.max_range for log in dataset.robots.values())
    track = np.concatenate(tracks)
    if not len(track):
        return {}
    passed = np.array([np.min(np.hypot(*(track - b).T)) <= reach for b in dataset.landmarks])
    fitted, aligned = aligned_map_error(means, dataset.landmarks)
    nearest = np.linalg.norm(aligned[:, None] - dataset.landmarks[None], axis=-1).min(0)
    return {"beacons_passed": int(passed.sum()), "beacons_mapped_within_0_3m": int((passed & (nearest <= within)).sum()),
            "spurious_after_fit": fitted["spurious"]}


def _ms(value: float | None) -> float | None:
    return None if value is None else round(value, 2)


def _rounded(values: dict) -> dict:
    return {k: None if v is None else round(float(v), 3) for k, v in values.items()}

