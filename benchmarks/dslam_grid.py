"""The grid simulation of Wang, Huang, Dissanayake, "Implementation Issues and Experimental Evaluation of
D-SLAM" (paper 003): D-SLAM against the EKF-SLAM baseline ("traditional SLAM").

World ``grid196`` (196 features at 3 m spacing in a 40 m square; 0.2 m/s,
0.1 rad/s, 180° field of view, 5 m range), one robot on a bounded random walk,
known association for both filters (the comparison is about estimation).
Per seed: map error, map NEES (joint, with the full information matrix / the
EKF's landmark covariance; and per landmark), robot pose NEES over time, the
ratio of D-SLAM's to EKF's landmark standard deviations (D-SLAM should be more
conservative), time per scan. The sparsity of D-SLAM's information matrix is
drawn as a PNG: the links between features (Fig. 3c of the paper) and the
non-zero pattern (Fig. 3d).

    .venv/bin/python benchmarks/dslam_grid.py --seeds 3 --duration 900 --out reports/dslam/grid.json
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # small dense algebra: threads only add overhead

import argparse
import time
from pathlib import Path

import numpy as np
from scipy.stats import chi2

from schemas.contract import OdomEvent, ScanEvent
from robots.simulator import simulate
from services.dslam.core import DSlam
from schemas.contract import RunOptions
from services.estimators import make_estimator
from report import emit


def run_filter(estimator, data):
    """Feed every event; return per-scan (stamp, pose NEES, position error) and per-scan seconds."""
    log = next(iter(data.robots.values()))
    rid = log.robot_id
    nees, errors, seconds = [], [], []
    for event in data.events():
        if isinstance(event, OdomEvent):
            estimator.on_odometry(event)
            continue
        if not isinstance(event, ScanEvent):
            continue
        tick = time.perf_counter()
        estimator.on_scan(event)
        seconds.append(time.perf_counter() - tick)
        pose, cov = estimator.poses()[rid]
        error = pose - log.truth_at(np.array([event.stamp]))[0]
        error[2] = (error[2] + np.pi) % (2 * np.pi) - np.pi
        nees.append(float(error @ np.linalg.solve(cov, error)))
        errors.append(float(np.hypot(error[0], error[1])))
    return np.array(nees), np.array(errors), np.array(seconds)


def map_figures(means, covs, ids, truth, joint_nees):
    error = means - truth[ids]
    marginal = np.einsum("ni,nij,nj->n", error, np.linalg.inv(covs), error)
    n = ids.shape[0]
    low, high = chi2.ppf([0.025, 0.975], 2 * n)
    return {
        "landmarks": int(n),
        "map_rmse_m": float(np.sqrt(np.mean(np.sum(error**2, axis=1)))),
        "map_nees_joint": float(joint_nees),
        "map_nees_joint_dof": int(2 * n),
        "map_nees_joint_band95": [float(low), float(high)],
        "map_nees_joint_consistent": bool(joint_nees <= high),
        "marginal_nees_mean": float(marginal.mean()),
        "mean_std_m": float(np.mean(np.sqrt(np.trace(covs, axis1=1, axis2=2) / 2))),
    }


def one_seed(seed: int, duration: float, rate: float, with_ekf: bool) -> dict:
    data = simulate("grid196", robots=1, seed=seed, duration=duration, rate=rate)
    out: dict = {"seed": seed}
    dslam = make_estimator(RunOptions(estimator="dslam", association="known"), [data.robots["r1"].info])
    nees, errors, seconds = run_filter(dslam, data)
    view = dslam.landmark_map()
    joint = dslam.map.normalised_error(data.landmarks[view.ids])
    out["dslam"] = {**map_figures(view.means, view.covs, view.ids, data.landmarks, joint),
                    "pose_rmse_m": float(np.sqrt(np.mean(errors**2))), "pose_nees": nees,
                    "ms_per_scan_median": float(np.median(seconds) * 1e3), "ms_per_scan_p99": float(np.percentile(seconds, 99) * 1e3),
                    "info_nnz": dslam.map.matrix.nnz, "info_blocks": dslam.map.matrix.blocks}
    out["_dslam"] = dslam
    if with_ekf:
        ekf = make_estimator(RunOptions(estimator="ekf", association="known"), [data.robots["r1"].info])
        nees_e, errors_e, seconds_e = run_filter(ekf, data)
        view_e = ekf.landmark_map()
        error = (view_e.means - data.landmarks[view_e.ids]).ravel()
        joint_e = float(error @ np.linalg.solve(ekf.P[3:, 3:], error))
        out["ekf"] = {**map_figures(view_e.means, view_e.covs, view_e.ids, data.landmarks, joint_e),
                      "pose_rmse_m": float(np.sqrt(np.mean(errors_e**2))), "pose_nees": nees_e,
                      "ms_per_scan_median": float(np.median(seconds_e) * 1e3),
                      "ms_per_scan_p99": float(np.percentile(seconds_e, 99) * 1e3)}
        common, ia, ib = np.intersect1d(view.ids, view_e.ids, return_indices=True)
        ratio = np.sqrt(np.trace(view.covs[ia], axis1=1, axis2=2) / np.trace(view_e.covs[ib], axis1=1, axis2=2))
        out["std_ratio_dslam_over_ekf_median"] = float(np.median(ratio))
        out["std_ratio_dslam_over_ekf_min"] = float(np.min(ratio))
    return out


def pose_consistency(runs: list[np.ndarray]) -> dict:
    """Average pose NEES over the seeds at each scan, against the two-sided 95 % band of χ²(3·runs)/runs."""
    k = min(len(r) for r in runs)
    stacked = np.stack([r[:k] for r in runs])
    average = stacked.mean(axis=0)
    low, high = chi2.ppf([0.025, 0.975], 3 * len(runs)) / len(runs)
    return {"mean": float(stacked.mean()), "band95_of_seed_average": [float(low), float(high)],
            "fraction_in_band": float(np.mean((average >= low) & (average <= high))),
            "fraction_above_band": float(np.mean(average > high)), "dof": 3}


def draw_sparsity(dslam: DSlam, truth: np.ndarray, path: Path) -> None:
    """Links among features (off-diagonal blocks) and the non-zero pattern of the information matrix."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection

    matrix = dslam.map.matrix.tocsr()
    n = dslam.map.n
    pattern = matrix.toarray().reshape(n, 2, n, 2).any(axis=(1, 3))
    i, j = np.nonzero(np.triu(pattern, 1))
    means = dslam.map.means
    fig, (left, right) = plt.subplots(1, 2, figsize=(12, 6))
    left.add_collection(LineCollection(np.stack([means[i], means[j]], 1), linewidths=0.4, colors="tab:blue", alpha=0.6))
    left.plot(truth[:, 0], truth[:, 1], "k+", ms=4, label="true features")
    left.plot(means[:, 0], means[:, 1], "r.", ms=4, label="D-SLAM estimates")
    left.set_aspect("equal")
    left.set_title(f"links in the information matrix ({i.size} feature pairs)")
    left.legend(loc="upper right", fontsize=8)
    right.spy(matrix, markersize=0.3)
    right.set_xlabel(f"non-zeros of I: {matrix.nnz} of {matrix.shape[0] ** 2} ({100 * matrix.nnz / matrix.shape[0] ** 2:.1f} %)")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def summarise(runs: list[dict], name: str) -> dict:
    keys = ["landmarks", "map_rmse_m", "map_nees_joint", "marginal_nees_mean", "mean_std_m", "pose_rmse_m",
            "ms_per_scan_median", "ms_per_scan_p99"]
    out = {k: float(np.mean([r[name][k] for r in runs])) for k in keys}
    dof = sum(r[name]["map_nees_joint_dof"] for r in runs)
    total = sum(r[name]["map_nees_joint"] for r in runs)
    low, high = chi2.ppf([0.025, 0.975], dof)
    out["map_nees_joint_per_dof"] = total / dof
    out["map_nees_joint_band95_per_dof"] = [float(low / dof), float(high / dof)]
    out["map_nees_consistent_runs"] = int(sum(r[name]["map_nees_joint_consistent"] for r in runs))
    out["pose_nees"] = pose_consistency([r[name]["pose_nees"] for r in runs])
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--duration", type=float, default=900.0, help="seconds of robot time per run")
    parser.add_argument("--rate", type=float, default=10.0, help="scan rate (Hz)")
    parser.add_argument("--no-ekf", action="store_true", help="skip the EKF-SLAM baseline")
    parser.add_argument("--png", default="docs/figures/dslam_grid_sparsity.png")
    parser.add_argument("--out", help="write the JSON here too")
    args = parser.parse_args()
    started = time.perf_counter()
    runs = [one_seed(seed, args.duration, args.rate, not args.no_ekf) for seed in range(args.seeds)]
    truth = simulate("grid196", duration=0.1).landmarks
    draw_sparsity(runs[0]["_dslam"], truth, Path(args.png))
    result = {
        "benchmark": "dslam_grid",
        "setup": {"world": "grid196", "seeds": args.seeds, "duration_s": args.duration, "rate_hz": args.rate,
                  "association": "known", "trajectory": "bounded random walk, 0.2 m/s, turns of 0.1 rad/s"},
        "dslam": summarise(runs, "dslam"),
        "sparsity": {"png": args.png, "info_nnz": runs[0]["dslam"]["info_nnz"], "info_blocks": runs[0]["dslam"]["info_blocks"],
                     "landmarks": runs[0]["dslam"]["landmarks"]},
        "wall_s": time.perf_counter() - started,
    }
    if not args.no_ekf:
        result["ekf"] = summarise(runs, "ekf")
        result["std_ratio_dslam_over_ekf_median"] = float(np.median([r["std_ratio_dslam_over_ekf_median"] for r in runs]))
        result["std_ratio_dslam_over_ekf_min"] = float(np.min([r["std_ratio_dslam_over_ekf_min"] for r in runs]))
    emit(result, args.out)


if __name__ == "__main__":
    main()
