"""D-SLAM's map against the batch optimum on the same information.

The D-SLAM filter linearises every measurement once, at the estimate of the
moment (eq. 10). The batch optimum uses the very same measurements (the phase-I
positions and every z_map with its R_map, recorded during the run) and solves
the nonlinear least-squares problem min Σ νᵀ R⁻¹ ν to convergence by
Gauss-Newton on the sparse normal equations. The figures: how far the filter's
map is from the optimum (in metres and in the filter's own covariance), the
errors of both against the truth, the cost at both, and the difference between
the filter's information matrix and the Hessian at the optimum.

    .venv/bin/python benchmarks/dslam_batch.py --seeds 3 --duration 600 --out reports/dslam/batch.json
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import time

import numpy as np
import scipy.sparse.linalg
from scipy.stats import chi2

from schemas.contract import OdomEvent, ScanEvent
from robots.simulator import simulate
from services.dslam.config import DslamConfig
from services.dslam.core import DSlam
from services.dslam.information_filter import BlockSparseMatrix, block_rows
from services.dslam.recast import innovation, map_measurement
from report import emit


def normal_equations(measurements, means: np.ndarray) -> tuple[BlockSparseMatrix, np.ndarray, float]:
    """Hessian JᵀR⁻¹J, gradient JᵀR⁻¹ν and cost νᵀR⁻¹ν of every recorded measurement at ``means`` (n, 2)."""
    hessian = BlockSparseMatrix()
    hessian.grow(means.shape[0])
    gradient = np.zeros(means.size)
    cost = 0.0
    for kind, index, z, cov in measurements:
        if kind == "absolute":
            nu = z.ravel() - means[index].ravel()
            jac = np.eye(nu.shape[0])
        else:
            predicted, jac3 = map_measurement(means[index])
            nu = innovation(z, predicted)
            jac = jac3.reshape(jac3.shape[0], -1)
        weighted = np.linalg.solve(cov, np.column_stack([jac, nu]))
        hessian.add(index, jac.T @ weighted[:, :-1])
        gradient[block_rows(index)] += jac.T @ weighted[:, -1]
        cost += float(nu @ weighted[:, -1])
    return hessian, gradient, cost


def batch_optimum(measurements, start: np.ndarray, iterations: int = 30, tol: float = 1e-10):
    """Gauss-Newton from ``start`` (n, 2); returns (optimum, Hessian at it, cost, iterations)."""
    means = start.copy()
    for done in range(1, iterations + 1):
        hessian, gradient, cost = normal_equations(measurements, means)
        step = scipy.sparse.linalg.splu(hessian.tocsr().tocsc()).solve(gradient)
        means = means + step.reshape(-1, 2)
        if np.max(np.abs(step)) < tol:
            break
    hessian, _, cost = normal_equations(measurements, means)
    return means, hessian, cost, done


def one_seed(seed: int, duration: float) -> dict:
    data = simulate("grid196", robots=1, seed=seed, duration=duration)
    dslam = DSlam(DslamConfig(association="known"), record=True)
    dslam.add_robot(data.robots["r1"].info)
    for event in data.events():
        if isinstance(event, OdomEvent):
            dslam.on_odometry(event)
        elif isinstance(event, ScanEvent):
            dslam.on_scan(event)
    filtered = dslam.map.means.copy()
    truth = data.landmarks[np.asarray(dslam.ids)]
    started = time.perf_counter()
    optimum, hessian, cost_optimum, iterations = batch_optimum(dslam.measurements, filtered)
    batch_s = time.perf_counter() - started
    _, _, cost_filter = normal_equations(dslam.measurements, filtered)
    gap = (filtered - optimum).ravel()
    info = dslam.map.matrix.tocsr()
    rows = sum(z.size for _, _, z, _ in dslam.measurements)
    dof = rows - optimum.size
    return {
        "seed": seed, "landmarks": int(optimum.shape[0]), "measurements": len(dslam.measurements), "rows": int(rows),
        "filter_vs_optimum_rms_m": float(np.sqrt(np.mean(np.sum((filtered - optimum) ** 2, axis=1)))),
        "filter_vs_optimum_max_m": float(np.max(np.linalg.norm(filtered - optimum, axis=1))),
        "filter_vs_optimum_mahalanobis": float(gap @ (info @ gap)),
        "filter_rmse_to_truth_m": float(np.sqrt(np.mean(np.sum((filtered - truth) ** 2, axis=1)))),
        "optimum_rmse_to_truth_m": float(np.sqrt(np.mean(np.sum((optimum - truth) ** 2, axis=1)))),
        "cost_filter": cost_filter, "cost_optimum": cost_optimum, "cost_dof": int(dof),
        "cost_optimum_band95": [float(v) for v in chi2.ppf([0.025, 0.975], dof)],
        "information_vs_hessian_relative": float(scipy.sparse.linalg.norm(info - hessian.tocsr()) / scipy.sparse.linalg.norm(info)),
        "gauss_newton_iterations": iterations, "batch_s": batch_s,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--duration", type=float, default=600.0)
    parser.add_argument("--out")
    args = parser.parse_args()
    runs = [one_seed(seed, args.duration) for seed in range(args.seeds)]
    keys = [k for k in runs[0] if isinstance(runs[0][k], float)]
    result = {"benchmark": "dslam_batch", "setup": {"world": "grid196", "duration_s": args.duration, "seeds": args.seeds,
                                                    "association": "known"},
              "mean": {k: float(np.mean([r[k] for r in runs])) for k in keys}, "runs": runs}
    emit(result, args.out)


if __name__ == "__main__":
    main()
