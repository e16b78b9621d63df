"""What each step of unknown association buys on real data, over seeds (median and worst, never the best).

Steps (FastSLAM, 100 particles, scans' ids ignored):

- ``nn``: per-particle maximum likelihood, the former default;
- ``shared-exact-no-tentative``: one optimal one-to-one assignment per scan on the filter's marginal map for
  every particle, new landmarks weigh at once (``confirm_hits=1``);
- ``shared-exact``: ... and new landmarks stay tentative (no weight, not mapped) until seen 3 times;
- ``shared-jcbb-fastslam1``: ... with joint compatibility (JCBB) instead, poses drawn from the motion model alone;
- ``shared-jcbb-no-robots``: ... and each scan folded into the proposal (FastSLAM 2.0), the robots' detections of
  each other ignored (the default before they weighed the particles);
- ``shared-jcbb-no-reacquire``: ... and those detections weighing the particles (the default before robots blind
  too long re-acquired the map);
- ``shared-jcbb``: ... and a robot whose dead reckoning has drifted beyond what scan-by-scan association can trust
  held until one rigid correction puts its recent detections back on the map (``reacquire``), or one within 1σ of
  its dead reckoning explains as many, every correction scored less half its squared size in σ of the drift, and
  a robot whose detections of other robots contradict its pose held too, those detections voting in its search
  (``reacquire_by_robots``): ``--association unknown``, the default;
- ``shared-jcbb-no-by-robots``: ``shared-jcbb`` without the robots' say in re-acquisition (the default before);
- ``shared-jcbb-drift-reset``: ``shared-jcbb`` with a robot's drift started from zero at every match (the default
  before a match conditioned it on the matched detections, ``reacquire_drift_update``);
- ``shared-jcbb-confirm-tol-1``: ``shared-jcbb`` whose confirmation takes, of the corrections near the dead reckoning
  within one detection of the best, the nearest (``reacquire_confirm_tolerance``; one landmark leaves the turn
  free, and the best by a fraction can be the window's edge);
- ``shared-jcbb-rigid-only``: ``shared-jcbb`` with the rigid correction alone (the default before: no correction
  near the dead reckoning taken on one landmark, no prior on the corrections);
- ``shared-jcbb-no-prior``: ``shared-jcbb`` without the prior (corrections near the dead reckoning confirmed);
- ``shared-jcbb-ess-0.05``: ... resampling only when the effective sample size falls below 5 % (not 50 %);
- ``shared-jcbb-unique``: ``shared-jcbb`` keeping only the pairings no other jointly compatible hypothesis with as
  many pairings does without (``unique_pairs``);
- ``shared-jcbb-turn-slip``: ``shared-jcbb`` with the heading variance per radian turned the robots announce
  (``turn_slip``: MR.CLAM's 0.015; the other data sets announce none);
- ``shared-jcbb-motion-1``, ``shared-jcbb-motion-0.25``: ``shared-jcbb`` with the robots' odometry covariance scaled
  by 1 or 0.25 (``motion_noise_scale``) in the particles' draws and the drift;
- ``shared-jcbb-turn-gain``: ``shared-jcbb`` with a turn gain per particle and robot (``turn_gain_std=0.04``,
  ``turn_gain_walk=0.002``): particles carry hypotheses of how much each robot's odometry over-counts its turns.

Steps (D-SLAM, ``--association unknown``: the association service's ``auto``; deterministic, so one run):

- ``dslam-per-scan``: z_map one scan at a time (the paper), gating on the CI-localised pose alone;
- ``dslam-floor``: ... gating with ``gate_pose_floor`` added to the pose covariance;
- ``dslam-local-map``: ... and scans with fewer than two mapped features collected into local maps;
- ``dslam-turn-slip``: ... and the heading variance per radian turned the robots announce (MR.CLAM's 0.015;
  the other data sets announce none), summed since the last localization, added to the association's gate;
- ``dslam-reacquire``: ... and re-acquisition of a lost robot (``reacquire``: position std beyond 1 m, detections
  held until one rigid correction against the map is clear): the default;
- ``dslam-no-by-robots``: the default without the robots' say in re-acquisition (``reacquire_by_robots``: a robot
  its detections of two other robots contradict is lost, and those detections vote in its search; the default before);
- ``dslam-unique``: the default with ``unique_pairs``.

Data: MR.CLAM 6 (five robots in one filter), Victoria Park (GPS), ACFR car park (GPS and surveyed beacons).
Per run: every robot's ATE (raw: the start poses are given), GPS RMSE, map RMSE and landmarks mapped,
matched within 1 m, spurious, and the surveyed landmarks the truth passes within sensor range of, mapped
within 0.3 m after the map's rigid fit to the survey; per step the median and the worst over the seeds.

    .venv/bin/python benchmarks/association_ablation.py [--steps nn,shared-jcbb] [--seeds 10] [--first-seed 0]
        [--data mrclam:,victoria-park:,car-park:] [--jobs 2] [--out FILE]
"""

from __future__ import annotations

import argparse
from concurrent.futures import ProcessPoolExecutor

import numpy as np

from report import emit, over_seeds
from robots.loaders import load_dataset
from schemas.contract import RunOptions
from support.fastslam_experiments import passed_beacons, run_and_score

STEPS: dict[str, tuple[str, str, dict]] = {
    "nn": ("fastslam", "nn", {}),
    "shared-exact-no-tentative": ("fastslam", "shared", {"shared_solver": "exact", "confirm_hits": 1,
                                                         "proposal": "fastslam1"}),
    "shared-exact": ("fastslam", "shared", {"shared_solver": "exact", "proposal": "fastslam1"}),
    "shared-jcbb-fastslam1": ("fastslam", "unknown", {"proposal": "fastslam1"}),
    "shared-jcbb-no-robots": ("fastslam", "unknown", {"robot_detections": False}),
    "shared-jcbb-no-reacquire": ("fastslam", "unknown", {"reacquire": False}),
    "shared-jcbb": ("fastslam", "unknown", {}),
    "shared-jcbb-rigid-only": ("fastslam", "unknown", {"reacquire_confirm_sigmas": 0.0, "reacquire_prior_weight": 0.0}),
    "shared-jcbb-no-prior": ("fastslam", "unknown", {"reacquire_prior_weight": 0.0}),
    "shared-jcbb-ess-0.05": ("fastslam", "unknown", {"resample_ess": 0.05}),
    "shared-jcbb-drift-reset": ("fastslam", "unknown", {"reacquire_drift_update": False}),
    "shared-jcbb-robot-sd-0": ("fastslam", "unknown", {"robot_detection_position_sd": 0.0}),
    "shared-jcbb-robot-sd-0.2": ("fastslam", "unknown", {"robot_detection_position_sd": 0.2}),
    "shared-jcbb-robot-sd-0.4": ("fastslam", "unknown", {"robot_detection_position_sd": 0.4}),
    "shared-jcbb-confirm-tol-1": ("fastslam", "unknown", {"reacquire_confirm_tolerance": 1.0}),
    "shared-jcbb-no-by-robots": ("fastslam", "unknown", {"reacquire_by_robots": False}),
    "shared-jcbb-robots-veto": ("fastslam", "unknown", {"reacquire_robots_veto": 3}),
    "shared-jcbb-no-robots-fit": ("fastslam", "unknown", {"reacquire_robots_fit_min": 10**6}),
    "dslam-per-scan": ("dslam", "unknown", {"local_map_max_std": 0.0, "gate_pose_floor": (0.0, 0.0, 0.0),
                                            "turn_slip": False, "reacquire": False}),
    "dslam-floor": ("dslam", "unknown", {"local_map_max_std": 0.0, "turn_slip": False, "reacquire": False}),
    "dslam-local-map": ("dslam", "unknown", {"turn_slip": False, "reacquire": False}),
    "dslam-turn-slip": ("dslam", "unknown", {"reacquire": False}),
    "dslam-reacquire": ("dslam", "unknown", {}),
    "dslam-no-by-robots": ("dslam", "unknown", {"reacquire_by_robots": False}),
    "shared-jcbb-unique": ("fastslam", "unknown", {"unique_pairs": True}),
    "shared-jcbb-turn-slip": ("fastslam", "unknown", {"turn_slip": True}),
    "shared-jcbb-turn-gain": ("fastslam", "unknown", {"turn_gain_std": 0.04, "turn_gain_walk": 0.002}),
    "shared-jcbb-motion-1": ("fastslam", "unknown", {"motion_noise_scale": 1.0}),
    "shared-jcbb-motion-0.25": ("fastslam", "unknown", {"motion_noise_scale": 0.25}),
    "dslam-unique": ("dslam", "unknown", {"unique_pairs": True}),
}
DETERMINISTIC = {"dslam"}  # estimators without random draws: one seed is every seed


def one_run(spec: str, step: str, seed: int, particles: int) -> dict:
    estimator, association, settings = STEPS[step]
    dataset = load_dataset(spec)
    run = run_and_score(dataset, RunOptions(estimator, association, particles, seed, dict(settings)))
    ate = [v for v in run["ate_rmse_m"].values() if v is not None]
    gps = [v for v in run.get("gps_rmse_m", {}).values() if v is not None]
    marks = run.get("landmarks") or {}
    beacons = passed_beacons(dataset, run["map_means"])
    return beacons | {"data": spec, "step": step, "seed": seed, "wall_s": run["wall_s"],
            "ate_robot_median_m": float(np.median(ate)) if ate else None, "ate_robot_worst_m": max(ate, default=None),
            "ate_rmse_m": run["ate_rmse_m"], "gps_rmse_m": float(np.mean(gps)) if gps else None,
            "map_rmse_m": run.get("map_rmse_m"), "landmarks_mapped": run["landmarks_mapped"],
            "landmarks_true": None if dataset.landmarks is None else int(len(dataset.landmarks)),
            "matched": marks.get("matched"), "spurious": marks.get("spurious")}


def summarise(runs: list[dict]) -> dict:
    """Median and worst over the seeds of every figure (worst: the largest, for errors and counts alike)."""
    keys = ("ate_robot_median_m", "ate_robot_worst_m", "gps_rmse_m", "map_rmse_m", "landmarks_mapped", "spurious",
            "matched", "beacons_passed", "beacons_mapped_within_0_3m", "spurious_after_fit", "wall_s")
    return {"seeds": len(runs), **over_seeds(runs, keys, least=True)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", default="mrclam:,victoria-park:,car-park:", help="data set specs, comma-separated")
    parser.add_argument("--steps", default=",".join(STEPS), help=f"comma-separated, of: {', '.join(STEPS)}")
    parser.add_argument("--seeds", type=int, default=10, help="how many seeds: FIRST..FIRST+N-1")
    parser.add_argument("--first-seed", type=int, default=0, help="the first seed (held-out seeds: e.g. 10)")
    parser.add_argument("--particles", type=int, default=100)
    parser.add_argument("--jobs", type=int, default=2, help="runs in parallel (processes)")
    parser.add_argument("--out")
    args = parser.parse_args()
    steps = args.steps.split(",")
    unknown = [s for s in steps if s not in STEPS]
    if unknown:
        parser.error(f"unknown steps {unknown}; choose from {', '.join(STEPS)}")
    jobs = [(spec, step, seed) for spec in args.data.split(",") for step in steps
            for seed in range(args.first_seed, args.first_seed + (1 if STEPS[step][0] in DETERMINISTIC else args.seeds))]
    with ProcessPoolExecutor(max_workers=args.jobs) as pool:
        runs = list(pool.map(one_run, *zip(*jobs), [args.particles] * len(jobs)))
    report: dict = {"settings": vars(args), "runs": runs, "summary": {}}
    for spec in args.data.split(","):
        report["summary"][spec] = {step: summarise([r for r in runs if r["data"] == spec and r["step"] == step])
                                   for step in steps}
    emit(report, args.out)


if __name__ == "__main__":
    main()
