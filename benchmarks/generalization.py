"""Unknown association and fleet placement on every data set at hand, over seeds: what holds on data never tuned on.

Every run is without landmark ids (``--association unknown``). Data sets: MR.CLAM 1, 2, 4 and 6, Victoria Park and
the ACFR car park; estimators FastSLAM and D-SLAM; start poses known or none (MR.CLAM only: with one robot, no start
pose is the known one up to the frame). Per data set, estimator and start mode, the median and the worst over the
seeds (never the best) of:

- ``ate_robot_worst_m`` / ``ate_robot_median_m``: each robot's position error. MR.CLAM 6 against Vicon; MR.CLAM 1,
  2 and 4, which have no robot truth, against the same seed's FastSLAM run *with barcodes* and the same start poses
  (its trajectories stand in for the truth); raw on MR.CLAM 6 with start poses known, otherwise after one SE(2)
  transform for the whole fleet (:func:`services.evaluation.metrics.fleet_alignment`: the derived start poses
  are estimates with a covariance, and two runs from them may turn as a whole);
  ``ate_ratio_worst``: the largest ratio of a robot's error to its error in the barcode run (MR.CLAM 6), or without
  start poses to the same seed's known-start run;
- ``map_rmse_m``, ``spurious``, ``missed``: the map registered to the survey from the map alone
  (:func:`services.evaluation.metrics.map_alignment`; the fleet's transform when the map is too large for that);
- ``gps_rmse_m`` (Victoria Park, car park), ``beacons_within_0_3m`` (car park);
- ``wall_s``, and for placement ``unplaced`` robots and ``placed_after_first_scan_s``.

MR.CLAM 1, 2 and 4 have no start poses either. Theirs (``support/mrclam_start_poses.json``) are fitted to the
survey from each robot's first detections with barcodes and its dead reckoning over those seconds
(:func:`survey_start_pose`), and announced with that fit's covariance. ``--derive-start-poses`` makes that file
again and checks the procedure on MR.CLAM 6 against Vicon.

D-SLAM draws nothing at random. With start poses known, its seed s ≥ 1 draws each robot's start pose from the
covariance it is announced with (:func:`services.placement.draw_start_poses`; seed 0 takes them as given), so
its figures too are a median and a worst over seeds. FastSLAM's seeds are its particles' draws.

Tune on some data sets and judge on the others: ``--datasets`` chooses them.

    .venv/bin/python benchmarks/generalization.py [--datasets mrclam1,mrclam2,mrclam4,mrclam6,victoria-park,car-park]
        [--estimators fastslam,dslam] [--start-poses known,none] [--seeds 5] [--first-seed 0] [--particles 100]
        [--set KEY=VALUE ...] [--jobs 2] [--out FILE]
    .venv/bin/python benchmarks/generalization.py --derive-start-poses
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

import numpy as np

from report import emit, over_seeds, setting
from robots.dataset import Dataset
from robots.loaders import load_dataset
from robots.models import dead_reckon, integrate_controls, robot_models, se2_compose, wrap_angle
from schemas.contract import RunOptions
from services.evaluation.metrics import Trajectory, fleet_alignment, map_alignment, map_error, score_estimates
from services.offline import run_estimator
from services.placement import draw_start_poses
from support.fastslam_experiments import passed_beacons

DATASETS = {
    "mrclam1": "mrclam:utias_mrclam/MRCLAM_Dataset1_partial",
    "mrclam2": "mrclam:utias_mrclam/MRCLAM_Dataset2_partial",
    "mrclam4": "mrclam:utias_mrclam/MRCLAM_Dataset4_partial",
    "mrclam6": "mrclam:utias_mrclam/MRCLAM_Dataset6",
    "victoria-park": "victoria-park:victoria_park",
    "car-park": "car-park:acfr_car_park",
}
START_POSES_FILE = Path(__file__).parent / "support" / "mrclam_start_poses.json"
DRAWN_START = {"dslam"}  # no random draws of its own: with start poses known, its seeds draw them (seed 0 as given)


# ---------------------------------------------------------------- start poses of the data sets without robot truth
def survey_start_pose(log, survey: np.ndarray, survey_ids: np.ndarray, min_detections: int = 20,
                      min_landmarks: int = 3, max_window_s: float = 60.0) -> dict:
    """A robot's pose at its first odometry stamp from its first detections *with barcodes* against the surveyed
    landmarks: the dead-reckoned path over the first seconds is rigid, and the one start pose that makes its
    detections fit the survey best (robust least squares, every start heading tried) is taken, with the
    covariance of that fit (Gauss-Newton) plus the odometry's over the window. Independent of every estimator."""
    from scipy.optimize import least_squares

    model, sensor = robot_models(log.info)
    begin = log.odom_stamp[0] - log.odom_dt[0]
    lookup = {int(i): k for k, i in enumerate(survey_ids)}
    scans = [s for s in range(log.scan_stamp.size)
             if log.scan_stamp[s] >= begin and log.scan_offsets[s + 1] > log.scan_offsets[s]]
    chosen, seen = [], set()
    for s in scans:
        chosen.append(s)
        seen |= {int(i) for i in log.det_id[log.scan_offsets[s]:log.scan_offsets[s + 1]] if int(i) in lookup}
        count = int(sum(log.scan_offsets[c + 1] - log.scan_offsets[c] for c in chosen))
        if (count >= min_detections and len(seen) >= min_landmarks) or log.scan_stamp[s] - begin > max_window_s:
            break
    stamps = log.scan_stamp[chosen]
    upto = log.odom_stamp <= stamps[-1] + 1e-9
    path = dead_reckon(model, log.odom_control[upto], log.odom_dt[upto])
    at = np.concatenate([[begin], log.odom_stamp[upto]])
    relative = np.stack([np.interp(stamps, at, path[:, 0]), np.interp(stamps, at, path[:, 1]),
                         np.interp(stamps, at, np.unwrap(path[:, 2]))], -1)
    rows = [(k, lookup[int(i)], log.det_range[d], log.det_bearing[d]) for k, s in enumerate(chosen)
            for d, i in zip(range(log.scan_offsets[s], log.scan_offsets[s + 1]),
                            log.det_id[log.scan_offsets[s]:log.scan_offsets[s + 1]]) if int(i) in lookup]
    which, marks = np.array([r[0] for r in rows]), survey[[r[1] for r in rows]]
    measured = np.array([[r[2], r[3]] for r in rows])
    sigma = np.sqrt(np.diag(log.scan_cov))

    def residuals(start: np.ndarray) -> np.ndarray:
        poses = se2_compose(start, relative[which])
        return (sensor.innovation(measured, sensor.observe(poses, marks)) / sigma).ravel()

    tries = []
    for heading in np.linspace(-np.pi, np.pi, 16, endpoint=False):
        guess = marks.mean(0) - 2.0 * np.array([np.cos(heading), np.sin(heading)])
        tries.append(least_squares(residuals, np.r_[guess, heading], loss="soft_l1"))
    best = min(tries, key=lambda r: r.cost)
    jac = best.jac
    fit_cov = np.linalg.pinv(jac.T @ jac)
    covs = np.broadcast_to(log.odom_cov, (int(upto.sum()), 2, 2)) if log.odom_cov.ndim == 2 else log.odom_cov[upto]
    _, odometry_cov = integrate_controls(model, log.odom_control[upto], log.odom_dt[upto], covs)
    pose = best.x.copy()
    pose[2] = wrap_angle(pose[2])
    return {"pose": pose.tolist(), "cov": (fit_cov + odometry_cov).tolist(), "detections": len(rows),
            "landmarks": len(seen), "window_s": round(float(stamps[-1] - begin), 2),
            "residual_rms_sigma": round(float(np.sqrt(np.mean(best.fun ** 2))), 2)}


SURVEY_SWAPS = {"mrclam1": (11, 17)}  # Dataset 1's survey holds landmarks 11 and 17 at each other's place (its loader)


def derive_start_poses(name: str) -> dict:
    """Start poses of a MR.CLAM data set in its survey's frame (:func:`survey_start_pose`, every robot)."""
    dataset = load_dataset(DATASETS[name])
    survey = dataset.landmarks.copy()
    if name in SURVEY_SWAPS:
        a, b = (int(np.flatnonzero(dataset.landmark_ids == i)[0]) for i in SURVEY_SWAPS[name])
        survey[[a, b]] = survey[[b, a]]
    return {"data": DATASETS[name],
            "robots": {rid: survey_start_pose(log, survey, dataset.landmark_ids) for rid, log in dataset.robots.items()}}


def with_start_poses(dataset: Dataset, name: str) -> Dataset:
    """``dataset`` with the derived start poses of :data:`START_POSES_FILE` where it has none of its own."""
    table = json.loads(START_POSES_FILE.read_text()).get(name) if START_POSES_FILE.exists() else None
    for rid, log in dataset.robots.items():
        if log.info.start_pose is None and table and rid in table["robots"]:
            entry = table["robots"][rid]
            log.info = log.info.model_copy(update={"start_pose": np.asarray(entry["pose"]),
                                                   "start_pose_cov": np.asarray(entry["cov"])})
    return dataset


# ---------------------------------------------------------------- one run
def trajectories_of(out) -> dict:
    return {rid: path for rid, path in out.trajectories.items() if len(path)}


def robot_errors(out, truth: dict, aligned: bool, truth_offset=(0.0, 0.0)) -> dict:
    """Each robot's position RMSE against ``truth`` (robot id → Trajectory): raw, or after one fleet transform."""
    if aligned:
        return fleet_alignment(out.trajectories, truth, truth_offset=truth_offset).get("ate_rmse_m", {})
    metrics, _ = score_estimates({"run": out.trajectories}, truth, {}, None, truth_offset)
    return metrics["summary"]["run"]["ate_rmse_m"]


def map_figures(dataset: Dataset, out, truth: dict, aligned: bool) -> dict:
    """The map against the survey after its own registration (or the fleet's transform when it is too large)."""
    if dataset.landmarks is None:
        return {"landmarks_mapped": int(len(out.map_means))}
    fit = map_alignment(out.map_means, dataset.landmarks)
    if fit:
        marks = fit["landmarks"]
        figures = {"map_rmse_m": fit["map_rmse_m"], "within_0_3m": fit["within_inlier"]}
    elif aligned and truth:
        fleet = fleet_alignment(out.trajectories, truth, true_landmarks=dataset.landmarks, map_means=out.map_means)
        marks, figures = fleet.get("landmarks", {}), {"map_rmse_m": fleet.get("map_rmse_m")}
    else:
        detail = map_error(out.map_means, dataset.landmarks)
        marks, figures = detail, {"map_rmse_m": detail["rmse_m"]}
    return figures | {"landmarks_mapped": int(len(out.map_means)), "spurious": marks.get("spurious"),
                      "missed": marks.get("missed")}


def one_run(name: str, estimator: str, association: str, start: str, seed: int, particles: int,
            settings: dict, truth: dict | None) -> dict:
    """One run under test, scored against ``truth`` (robot id → (stamps, poses)), or the data's own truth."""
    dataset = with_start_poses(load_dataset(DATASETS[name]), name)
    if estimator in DRAWN_START and start == "known":
        for log, info in zip(dataset.robots.values(), draw_start_poses([log.info for log in dataset.robots.values()], seed)):
            log.info = info
    cpu = time.process_time()
    out = run_estimator(dataset, RunOptions(estimator, association, particles, seed, dict(settings)),
                        start_poses=start)
    cpu = time.process_time() - cpu
    offset = tuple(dataset.meta.get("truth_offset", (0.0, 0.0)))
    # one SE(2) for the fleet without start poses, and against a barcode run: its start poses are estimates, and the
    # frame of two runs from them may turn as a whole (the survey fit's covariance allows it)
    aligned = start == "none" or truth is not None
    if truth is None:
        truth = {rid: Trajectory(log.truth_stamp, log.truth_pose) for rid, log in dataset.robots.items()
                 if log.truth_stamp.size}
    else:
        truth = {rid: Trajectory(np.asarray(s), np.asarray(p)) for rid, (s, p) in truth.items()}
    record = {"data": name, "estimator": estimator, "association": association, "start": start, "seed": seed,
              "wall_s": round(out.wall_s, 2), "cpu_s": round(cpu, 2),
              "trajectories": {rid: (path.stamps.tolist(), path.poses.tolist())
                               for rid, path in trajectories_of(out).items()}}
    if len(dataset.robots) > 1:
        errors = robot_errors(out, truth, aligned)
        placed = {rid: e for rid, e in errors.items() if e is not None}
        record["ate_m"] = {rid: round(float(e), 3) for rid, e in placed.items()}
        record["unplaced"] = sorted(set(dataset.robots) - set(placed))
        record["ate_robot_worst_m"] = None if record["unplaced"] else max(placed.values(), default=None)
        record["ate_robot_median_m"] = float(np.median(list(placed.values()))) if placed else None
        placement = out.extra.get("placement") or {}
        delays = [p.get("placed_after_first_scan_s") for p in placement.values()
                  if p.get("placed_after_first_scan_s") is not None]
        record["placed_after_first_scan_s"] = max(delays) if delays and not record["unplaced"] else None
    else:
        metrics, _ = score_estimates({"run": out.trajectories}, truth, {}, None, offset)
        gps = [v for v in metrics["summary"]["run"].get("gps_rmse_m", {}).values() if v is not None]
        record["gps_rmse_m"] = float(np.mean(gps)) if gps else None
    for key in ("noise_gain", "turn_scale"):
        if out.extra.get(key):
            record[key] = out.extra[key]
    record |= map_figures(dataset, out, truth, aligned)
    if name == "car-park":
        beacons = passed_beacons(dataset, out.map_means)
        record["beacons_within_0_3m"] = beacons.get("beacons_mapped_within_0_3m")
        record["beacons_passed"] = beacons.get("beacons_passed")
    return record


def barcode_runs(pool, jobs: list[tuple], cache: Path | None) -> dict:
    """The barcode runs of ``jobs``, (data, seed) → run; with ``cache``, each one kept there as JSON and reused by
    later reports (the runs under test change, the barcode runs do not while the known-association code does not)."""
    done, todo = {}, []
    for job in jobs:
        path = cache / f"{job[0]}-seed{job[4]}-p{job[5]}.json" if cache else None
        if path and path.exists():
            record = json.loads(path.read_text())
            for key in ("trajectories", "ate_m"):  # JSON turned the robot ids into strings
                record[key] = {int(rid) if rid.isdigit() else rid: v for rid, v in record.get(key, {}).items()}
            done[(job[0], job[4])] = record
        else:
            todo.append(job)
    for record in pool_map(pool, one_run, todo, "barcode run"):
        done[(record["data"], record["seed"])] = record
        if cache:
            cache.mkdir(parents=True, exist_ok=True)
            (cache / f"{record['data']}-seed{record['seed']}-p{jobs[0][5]}.json").write_text(json.dumps(record))
    return done


def reference_truth(record: dict) -> dict:
    return {rid: (np.asarray(s), np.asarray(p)) for rid, (s, p) in record["trajectories"].items()}


# ---------------------------------------------------------------- the table
KEYS = ("ate_robot_worst_m", "ate_robot_median_m", "ate_ratio_worst", "map_rmse_m", "spurious", "missed",
        "landmarks_mapped", "within_0_3m", "gps_rmse_m", "beacons_within_0_3m", "placed_after_first_scan_s",
        "wall_s")


def ratios(runs: list[dict], yardstick: dict) -> None:
    """Each run's ``ate_ratio_worst``: its robots' errors over ``yardstick``'s ((data, seed) → run) robot errors."""
    for run in runs:
        base = yardstick.get((run["data"], run["seed"]))
        if not base or not run.get("ate_m") or run.get("unplaced"):
            continue
        pairs = [(e, base["ate_m"].get(rid)) for rid, e in run["ate_m"].items()]
        run["ate_ratio_worst"] = max((e / b for e, b in pairs if b), default=None)


def summarise(runs: list[dict]) -> dict:
    """Per data set, estimator and start mode: the median and worst over the seeds of :data:`KEYS`; and without start
    poses ``wall_ratio_to_known``: the median run time over the known-start run's (issue 52: within 3)."""
    out: dict = {}
    for run in runs:
        out.setdefault(run["data"], {}).setdefault(run["estimator"], {}).setdefault(run["start"], []).append(run)
    table = {data: {est: {start: {"seeds": len(group), "unplaced_runs": sum(bool(r.get("unplaced")) for r in group),
                                  **over_seeds(group, KEYS)}
                          for start, group in by_start.items()}
                    for est, by_start in by_est.items()}
             for data, by_est in out.items()}
    for data, by_est in out.items():  # the car park's target: every beacon passed within 0.3 m, in most seeds
        for est, by_start in by_est.items():
            for start, group in by_start.items():
                counted = [r for r in group if r.get("beacons_passed")]
                if counted:
                    table[data][est][start]["seeds_with_every_beacon"] = (
                        f"{sum(r['beacons_within_0_3m'] == r['beacons_passed'] for r in counted)} of {len(counted)}")
    for by_est in table.values():
        for modes in by_est.values():
            if "known" in modes and "none" in modes and "wall_s" in modes["known"] and "wall_s" in modes["none"]:
                modes["none"]["wall_ratio_to_known"] = round(modes["none"]["wall_s"]["median"]
                                                             / max(modes["known"]["wall_s"]["median"], 1e-9), 2)
    return table


TABLE_KEYS = (("ate_robot_worst_m", "worst robot (m)"), ("ate_ratio_worst", "worst ratio"), ("map_rmse_m", "map (m)"),
              ("spurious", "spurious"), ("missed", "missed"), ("gps_rmse_m", "GPS (m)"),
              ("wall_s", "wall (s)"))


def markdown_table(reports: list[dict], names: list[str]) -> str:
    """One row per data set, estimator and start mode of any report; per figure 'median / worst' of each report
    (``names``), joined by ' → ': the before-and-after table a change is judged by."""
    extras = (("seeds_with_every_beacon", "every beacon ≤ 0.3 m"), ("wall_ratio_to_known", "wall / known start"))
    rows = ["| data | estimator | start | " + " | ".join(label for _, label in TABLE_KEYS + extras) + " |",
            "|---" * (3 + len(TABLE_KEYS) + len(extras)) + "|"]
    groups = {(data, est, start) for report in reports for data, by_est in report["summary"].items()
              for est, modes in by_est.items() for start in modes}
    for data, est, start in sorted(groups, key=lambda g: (list(DATASETS).index(g[0]), g[1] != "fastslam", g[2])):
        summaries = [report["summary"].get(data, {}).get(est, {}).get(start, {}) for report in reports]
        cells = []
        for key, _ in TABLE_KEYS:
            parts = ["–" if s.get(key) is None else f"{s[key]['median']:g} / {s[key]['worst']:g}" for s in summaries]
            cells.append(" → ".join(parts) if any(p != "–" for p in parts) else "")
        for key, _ in extras:
            parts = [str(s.get(key, "–")) for s in summaries]
            cells.append(" → ".join(parts) if any(p != "–" for p in parts) else "")
        rows.append(f"| {data} | {est} | {start} | " + " | ".join(cells) + " |")
    return f"({' → '.join(names)}; median / worst over seeds)\n\n" + "\n".join(rows)


def pool_map(pool, function, jobs: list[tuple], what: str) -> list:
    """``function`` over ``jobs`` in the pool, in order; a line on stderr as each run ends (runs take 1-60 s)."""
    futures = [pool.submit(function, *job) for job in jobs]
    for done, future in enumerate(as_completed(futures), 1):
        run = future.result()
        print(f"{what} {done}/{len(jobs)}: {run['data']} {run['estimator']} start {run['start']} seed {run['seed']} "
              f"{run['wall_s']:.0f} s", file=sys.stderr, flush=True)
    return [future.result() for future in futures]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--datasets", default=",".join(DATASETS), help=f"comma-separated, of: {', '.join(DATASETS)}")
    parser.add_argument("--estimators", default="fastslam,dslam")
    parser.add_argument("--start-poses", default="known,none",
                        help="comma-separated, of: known, none (none on MR.CLAM only)")
    parser.add_argument("--seeds", type=int, default=5, help="how many seeds: FIRST..FIRST+N-1")
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument("--particles", type=int, default=100)
    parser.add_argument("--set", dest="settings", type=setting, action="append", default=[],
                        help="KEY=VALUE of FastSLAM's settings for the runs under test (repeatable)")
    parser.add_argument("--dslam-set", dest="dslam_settings", type=setting, action="append", default=[],
                        help="KEY=VALUE of D-SLAM's settings for the runs under test (repeatable)")
    parser.add_argument("--jobs", type=int, default=2, help="runs in parallel (processes)")
    parser.add_argument("--derive-start-poses", action="store_true",
                        help=f"derive {START_POSES_FILE.name} for MR.CLAM 1, 2, 4 (and check it on MR.CLAM 6)")
    parser.add_argument("--table", nargs="+", metavar="REPORT",
                        help="print the markdown table of these reports (JSON written by --out), before → after")
    parser.add_argument("--barcode-particles", type=int,
                        help="particles of the barcode runs (default --particles): one yardstick for several counts")
    parser.add_argument("--barcode-cache", metavar="DIR",
                        help="keep the barcode runs here and reuse them (only while known association is unchanged)")
    parser.add_argument("--out")
    args = parser.parse_args()
    if args.table:
        print(markdown_table([json.loads(Path(f).read_text()) for f in args.table], args.table))
        return
    if args.derive_start_poses:
        with ProcessPoolExecutor(max_workers=args.jobs) as pool:
            names = ["mrclam1", "mrclam2", "mrclam4", "mrclam6"]
            table = dict(zip(names, pool.map(derive_start_poses, names)))
        vicon = load_dataset(DATASETS["mrclam6"])
        check = {rid: round(float(np.hypot(*(np.asarray(entry["pose"][:2]) - vicon.robots[rid].info.start_pose[:2]))), 3)
                 for rid, entry in table["mrclam6"]["robots"].items()}
        START_POSES_FILE.write_text(json.dumps({k: v for k, v in table.items() if k != "mrclam6"}, indent=1) + "\n")
        emit({"written": str(START_POSES_FILE), "mrclam6_start_error_m": check, "table": table}, args.out)
        return
    names, estimators = args.datasets.split(","), args.estimators.split(",")
    unknown = [n for n in names if n not in DATASETS]
    if unknown:
        parser.error(f"unknown data sets {unknown}; choose from {', '.join(DATASETS)}")
    modes = args.start_poses.split(",")
    if set(modes) - {"known", "none"}:
        parser.error(f"--start-poses takes known, none or known,none, not {args.start_poses!r}")
    seeds = list(range(args.first_seed, args.first_seed + args.seeds))
    settings = {"fastslam": dict(args.settings), "dslam": dict(args.dslam_settings)}
    truthless = [n for n in names if n in ("mrclam1", "mrclam2", "mrclam4")]
    started = time.time()
    with ProcessPoolExecutor(max_workers=args.jobs) as pool:
        # the barcode runs: the truth of MR.CLAM 1, 2, 4 and the yardstick of MR.CLAM 6's ratios
        barcode_jobs = [(n, "fastslam", "known", "known", s, args.barcode_particles or args.particles, {}, None)
                        for n in truthless + [n for n in names if n == "mrclam6"] for s in seeds]
        barcode = barcode_runs(pool, barcode_jobs, Path(args.barcode_cache) if args.barcode_cache else None)
        jobs = []
        for n in names:
            for est in estimators:
                for mode in modes if n.startswith("mrclam") else ["known"]:
                    for s in seeds:
                        truth = reference_truth(barcode[(n, s)]) if n in truthless else None
                        jobs.append((n, est, "unknown", mode, s, args.particles, settings[est], truth))
        runs = pool_map(pool, one_run, jobs, "run")
    ratios([r for r in runs if r["start"] == "known" and r["data"] == "mrclam6"],
           {k: v for k, v in barcode.items() if k[0] == "mrclam6"})
    for est in estimators:
        known = {(r["data"], r["seed"]): r for r in runs if r["estimator"] == est and r["start"] == "known"}
        ratios([r for r in runs if r["estimator"] == est and r["start"] == "none"], known)
    for run in list(barcode.values()) + runs:
        run.pop("trajectories", None)
    report = {"settings": vars(args) | {"settings": settings}, "wall_s": round(time.time() - started, 1),
              "summary": summarise(runs), "barcodes": summarise(list(barcode.values())), "runs": runs,
              "barcode_runs": list(barcode.values())}
    emit(report, args.out)


if __name__ == "__main__":
    main()
