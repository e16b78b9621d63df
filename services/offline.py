"""``fleetslam run``: feed a data set straight into an estimator, no Zenoh, as fast as the machine allows.

The data set's events (every robot's odometry and scans, merged in time order)
go to the estimator named by ``--estimator`` through the common protocol of
:mod:`schemas.contract` (built by :mod:`services.estimators`). Every ``--sample-period-s`` of data time the
estimator's poses are recorded (each stamped with its robot's last odometry
time), which gives the estimated trajectories; at the end its map is taken.
Both are scored against the truth (:mod:`services.evaluation.metrics`) and
written as JSON (``--json``) and, with ``--out``, as a report folder. An
estimator may add its own figures by offering ``extra_metrics() -> dict``.
Loaders, scoring and plotting are imported on first use (every ``fleetslam``
command imports this module for its flags).
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from robots.dataset import Dataset
from schemas.config import RunSettings, add_settings_arguments, settings_from_args
from schemas.contract import OdomEvent, RunOptions, ScanEvent, SettingsError

log = logging.getLogger("fleetslam.run")


@dataclass
class OfflineRun:
    """What one offline run produced: sampled trajectories, final map, timings, extra figures."""

    trajectories: dict  # robot id -> services.evaluation.metrics.Trajectory
    map_means: np.ndarray
    map_covs: np.ndarray | None
    map_ids: np.ndarray | None
    wall_s: float
    data_s: float
    events: dict[str, int]
    timing: dict[str, dict]
    extra: dict = field(default_factory=dict)


def load(settings: RunSettings) -> Dataset:
    """The data set of ``settings.dataset`` (a simulation takes the run's seed, duration and robots; a ROS 2 bag
    the fleet file ``settings.fleet_file``, default the bag's own ``fleet.yaml``)."""
    from robots.loaders import load_dataset

    kind = settings.dataset.partition(":")[0]
    if settings.fleet_file is not None and kind != "rosbag2":
        raise ValueError(f"--fleet is for rosbag2: data sets only (the data set is {settings.dataset})")
    if kind == "rosbag2":
        return load_dataset(settings.dataset, fleet=settings.fleet_file)
    if kind != "sim":
        return load_dataset(settings.dataset)
    robot_ids = settings.robot_ids.split(",") if settings.robot_ids else None
    return load_dataset(settings.dataset, robots=settings.sim_robots, robot_ids=robot_ids, seed=settings.seed,
                        duration=settings.duration or 60.0, rate=settings.sim_rate)


def default_start_poses(dataset: Dataset, robots: list[str]) -> str:
    """``known`` when every chosen robot of the data set has a start pose, else ``none``."""
    return "known" if all(dataset.robots[rid].info.start_pose is not None for rid in robots) else "none"


def run_estimator(dataset: Dataset, options: RunOptions, robots: list[str] | None = None,
                  duration: float | None = None, sample_period_s: float = 0.1, progress: bool = False,
                  start_poses: str | None = None, should_stop: Callable[[], bool] | None = None,
                  robot_meetings: bool = True) -> OfflineRun:
    """Drive the estimator ``options.estimator`` over the data set's events; sample its poses.

    ``start_poses`` (known | first | none; default :func:`default_start_poses`) withholds start poses; an
    estimator that can take robots without one gets them placed by :class:`services.placement.FleetPlacer`
    (``robot_meetings``: also by detections between robots, :mod:`services.mcl.meeting`). ``should_stop`` is
    asked between events (a signal handler's flag): when it says so, or on KeyboardInterrupt, the run ends there
    and what was computed is returned (``extra["interrupted"]``).
    """
    from services.estimators import make_estimator
    from services.evaluation.metrics import Trajectory, timing_stats
    from services.mcl.config import MclConfig
    from services.placement import FleetPlacer, withhold_start_poses

    chosen = robots or list(dataset.robots)
    missing = [rid for rid in chosen if rid not in dataset.robots]
    if missing:
        raise ValueError(f"robots {', '.join(missing)} are not in {dataset.name} (it has {', '.join(dataset.robots)})")
    mode = start_poses or default_start_poses(dataset, chosen)
    infos = withhold_start_poses([dataset.robots[rid].info for rid in chosen], mode)
    estimator = make_estimator(options, infos)
    log.info("running %s on %s: robots %s, %s s of data (Ctrl-C stops it and keeps what was computed)",
             options.estimator, dataset.name, ", ".join(chosen), "all" if duration is None else f"{duration:g}")
    placer = None
    if any(info.start_pose is None for info in infos) and hasattr(estimator, "place_robot"):
        placer = FleetPlacer(estimator, infos, MclConfig(seed=options.seed),
                             use_signatures=options.association == "known", meetings=robot_meetings)
    elif any(info.start_pose is None for info in infos) and options.estimator not in ("mcl", "odometry"):
        log.warning("%s cannot place robots without a start pose: they stay out", options.estimator)
    samples: dict[str, tuple[list, list, list]] = {rid: ([], [], []) for rid in chosen}
    pose_stamp = {rid: dataset.robots[rid].start_stamp for rid in chosen}
    start = min(dataset.robots[rid].start_stamp for rid in chosen)
    end = max(dataset.robots[rid].end_stamp for rid in chosen)
    if duration is not None:
        end = min(end, start + duration)

    def sample() -> None:
        for rid, (pose, cov) in estimator.poses().items():
            if rid not in samples:
                continue
            stamps, poses, covs = samples[rid]
            if stamps and stamps[-1] >= pose_stamp[rid]:
                poses[-1], covs[-1] = np.asarray(pose, float), np.asarray(cov, float)
                continue
            stamps.append(pose_stamp[rid])
            poses.append(np.asarray(pose, float))
            covs.append(np.asarray(cov, float))

    counts = {"odometry": 0, "scan": 0}
    held: Counter = Counter()
    odom_s: list[float] = []
    scan_s: list[float] = []
    next_sample = start
    last_stamp = start
    interrupted = False
    wall0 = time.perf_counter()
    sample()
    with Progress(TextColumn("[bold]{task.description}"), BarColumn(), TextColumn("{task.completed:.0f}/{task.total:.0f} s"),
                  TimeElapsedColumn(), console=Console(stderr=True), transient=True, disable=not progress) as bar:
        task = bar.add_task(f"{options.estimator} on {dataset.name}", total=max(end - start, 1e-9))
        next_refresh = wall0
        try:
            for event in dataset.events(duration, chosen):
                if should_stop is not None and should_stop():
                    raise KeyboardInterrupt
                tick = time.perf_counter()
                if placer is not None and placer.holds(event):
                    held[type(event).__name__] += 1
                    if isinstance(event, OdomEvent):  # once placed, its first pose holds from here on
                        pose_stamp[event.robot_id] = event.stamp
                elif isinstance(event, OdomEvent):
                    estimator.on_odometry(event)
                    odom_s.append(time.perf_counter() - tick)
                    pose_stamp[event.robot_id] = event.stamp
                    counts["odometry"] += 1
                elif isinstance(event, ScanEvent):
                    estimator.on_scan(event)
                    scan_s.append(time.perf_counter() - tick)
                    counts["scan"] += 1
                last_stamp = event.stamp
                if event.stamp >= next_sample:
                    sample()
                    next_sample = start + (np.floor((event.stamp - start) / sample_period_s) + 1) * sample_period_s
                if progress and tick >= next_refresh:
                    bar.update(task, completed=event.stamp - start)
                    next_refresh = tick + 0.25
        except KeyboardInterrupt:  # Ctrl-C or SIGTERM (see main), between two events: keep what was computed
            interrupted = True
            log.warning("interrupted after %.1f s of data: scoring and saving what was computed", last_stamp - start)
        sample()
    wall_s = time.perf_counter() - wall0
    view = estimator.landmark_map()
    extra = dict(estimator.extra_metrics()) if hasattr(estimator, "extra_metrics") else {}
    extra["start_poses"] = mode
    if interrupted:
        extra["interrupted"] = True
    if placer is not None:
        extra["placement"] = placer.report(start)
        extra["held_for_placement"] = {"odometry": held["OdomEvent"], "scan": held["ScanEvent"]}
        for rid, record in extra["placement"].items():
            if record["how"] is None:
                log.warning("robot %s was never placed: %s", rid, record["reason"] or "it never scanned")
    trajectories = {rid: Trajectory.from_lists(*samples[rid]) for rid in chosen if samples[rid][0]}
    return OfflineRun(
        trajectories=trajectories, map_means=np.asarray(view.means, float).reshape(-1, 2),
        map_covs=None if view.covs is None else np.asarray(view.covs, float).reshape(-1, 2, 2),
        map_ids=view.ids, wall_s=wall_s, data_s=last_stamp - start, events=counts,
        timing={"odometry": timing_stats(np.array(odom_s)), "scan": timing_stats(np.array(scan_s))}, extra=extra or {},
    )


def _meta_counts(meta: dict) -> dict:
    """The data set's small descriptive figures (counts, not arrays)."""
    return {k: v for k, v in meta.items() if not isinstance(v, np.ndarray)}


def parse_estimator_settings(text: str | None) -> dict:
    """``--set`` "a=1,b=x,c=true" -> {"a": 1, "b": "x", "c": True} (values read as JSON where they parse; the
    estimator's core configuration then checks names and types)."""
    values: dict = {}
    for item in filter(None, (part.strip() for part in (text or "").split(","))):
        name, sep, raw = item.partition("=")
        if not sep or not name.strip():
            raise SettingsError(f"--set expects NAME=VALUE pairs separated by commas, got {item!r}")
        try:
            values[name.strip()] = json.loads(raw)
        except json.JSONDecodeError:
            values[name.strip()] = raw.strip()
    return values


def run_options(settings: RunSettings, dataset: Dataset) -> RunOptions:
    """The estimator's options: the shared settings, its own ``--set`` ones, and what a localizer needs beyond
    the events (the data set's true map to localize against, and the truth to measure convergence)."""
    own = parse_estimator_settings(settings.estimator_settings)
    if settings.workers is not None and settings.estimator == "fastslam":  # --set workers=N, if given, wins
        own = {"workers": settings.workers, **own}
    options = RunOptions(estimator=settings.estimator, association=settings.association, particles=settings.particles,
                         seed=settings.seed, settings=own)
    if settings.estimator == "mcl":
        options.landmarks = dataset.landmarks
        options.landmark_ids = dataset.landmark_ids
        options.truth = {rid: (log.truth_stamp, log.truth_pose) for rid, log in dataset.robots.items()}
    if settings.map:  # a saved map: the one to start from, or (mcl) to localize against instead of the true one
        from services.maps import load_prior, options_with_map

        options = options_with_map(options, load_prior(settings.map))
    return options


def save_run_map(settings: RunSettings, result: OfflineRun, robots: list[str]) -> None:
    """Write the run's final map to ``settings.map_out`` (atomically), saying what made it; the outcome goes to
    ``result.extra`` (``map_out``, or ``map_out_error``: the run's figures are kept either way)."""
    from schemas.contract import MapView
    from schemas.mapfile import MapFileError, save_map

    covs = np.zeros((len(result.map_means), 2, 2)) if result.map_covs is None else result.map_covs
    source = {"estimator": settings.estimator, "association": settings.association, "particles": settings.particles,
              "seed": settings.seed, "settings": parse_estimator_settings(settings.estimator_settings),
              "dataset": settings.dataset, "robots": robots, "start_poses": result.extra.get("start_poses"),
              "data_s": round(result.data_s, 3), "interrupted": bool(result.extra.get("interrupted")),
              "from_map": settings.map}
    try:
        save_map(settings.map_out, MapView(result.map_means, covs, result.map_ids), source)
    except MapFileError as error:
        log.error("map not saved: %s", error)
        result.extra["map_out_error"] = str(error)
        return
    log.info("map of %d landmarks saved to %s", len(result.map_means), settings.map_out)
    result.extra["map_out"] = {"path": settings.map_out, "landmarks": len(result.map_means)}


def run(settings: RunSettings, console: Console | None = None, should_stop: Callable[[], bool] | None = None) -> dict:
    """Load, run, score; write the JSON and the report folder; return the results."""
    from services.evaluation.metrics import Trajectory, fleet_alignment, map_alignment, score_estimates
    from services.evaluation.report import clean_json, clear_report, write_report

    if settings.rerun:
        from services.viz import rerun_missing

        if missing := rerun_missing():
            raise ValueError(f"--rerun: {missing}")
    dataset = load(settings)
    robots = settings.robot_ids.split(",") if settings.robot_ids else None
    options = run_options(settings, dataset)
    result = run_estimator(dataset, options, robots, settings.duration, settings.sample_period_s,
                           progress=settings.progress, start_poses=settings.start_poses, should_stop=should_stop,
                           robot_meetings=settings.robot_meetings)
    chosen = robots or list(dataset.robots)
    if settings.map_out:
        save_run_map(settings, result, chosen)
    truth = {rid: Trajectory(dataset.robots[rid].truth_stamp, dataset.robots[rid].truth_pose) for rid in chosen
             if dataset.robots[rid].truth_stamp.size}
    name = settings.estimator
    if settings.rerun:
        from services.viz.recording import save_offline_run

        save_offline_run(settings.rerun, dataset, result, truth, name, settings.sample_period_s)
    maps = {name: (result.map_means, result.map_covs)}
    truth_offset = tuple(dataset.meta.get("truth_offset", (0.0, 0.0)))
    metrics, curves = score_estimates({name: result.trajectories}, truth, maps, dataset.landmarks, truth_offset,
                                      settings.map_cutoff_m, settings.rpe_delta_s)
    summary = metrics["summary"][name]
    detail = metrics["estimators"][name]["robots"]
    gps = list(summary.get("gps_rmse_m", {}).values())
    output = {
        "dataset": settings.dataset, "dataset_name": dataset.name, "estimator": name,
        "robots": chosen, "wall_s": result.wall_s, "data_s": result.data_s,
        "realtime_factor": result.data_s / result.wall_s if result.wall_s > 0 else None,
        "events": result.events,
        "ate_rmse_m": summary["ate_rmse_m"], "ate_aligned_rmse_m": summary["ate_aligned_rmse_m"],
        "gps_rmse_m": float(np.mean(gps)) if gps and all(g is not None for g in gps) else None,
        "heading_rmse_rad": {rid: m.get("heading_rmse_rad") for rid, m in detail.items() if "heading_rmse_rad" in m},
        "rpe": {rid: m["rpe"] for rid, m in detail.items() if "rpe" in m},
        "nees": {rid: m["nees"] for rid, m in detail.items() if "nees" in m},
        "map_rmse_m": summary["map_rmse_m"], "landmarks": summary["landmarks"],
        "fleet_aligned": fleet_alignment(result.trajectories, truth, true_landmarks=dataset.landmarks,
                                         map_means=result.map_means, map_cutoff=settings.map_cutoff_m,
                                         truth_offset=truth_offset),
        "map_aligned": map_alignment(result.map_means, dataset.landmarks, settings.map_cutoff_m)
        if not truth and dataset.landmarks is not None and result.map_means is not None
        and result.extra.get("start_poses") != "known" else {},
        "timing": result.timing,
        "settings": settings.model_dump(mode="json"),
        "dataset_meta": _meta_counts(dataset.meta),
    }
    output.update(result.extra)
    output = clean_json(output)
    if settings.out:
        metrics["run"] = output
        cleared = clear_report(settings.out)
        written = write_report(settings.out, metrics, curves, truth, {name: result.trajectories}, maps,
                               dataset.landmarks, dataset.name, truth_offset)
        output["report"] = str(Path(settings.out))
        results = Path(settings.out) / "results.json"
        results.write_text(json.dumps(output, indent=2))
        log.info("report in %s: %s%s", settings.out, ", ".join(p.name for p in [results, *written]),
                 f" ({cleared} files of an earlier report removed)" if cleared else "")
    if settings.json_out:
        Path(settings.json_out).parent.mkdir(parents=True, exist_ok=True)
        Path(settings.json_out).write_text(json.dumps(output, indent=2))
    return output


def print_results(output: dict, console: Console) -> None:
    table = Table(title=f"{output['estimator']} on {output['dataset_name']}: {output['data_s']:.1f} s of data "
                        f"in {output['wall_s']:.2f} s")
    for column in ("robot", "ATE raw (m)", "ATE aligned (m)", "heading RMSE (rad)"):
        table.add_column(column, justify="right")

    def fmt(value, digits=3):
        return "-" if value is None else f"{value:.{digits}f}"

    for rid in output["robots"]:
        table.add_row(rid, fmt(output["ate_rmse_m"].get(rid)), fmt(output["ate_aligned_rmse_m"].get(rid)),
                      fmt(output["heading_rmse_rad"].get(rid)))
    console.print(table)
    for rid, record in (output.get("placement") or {}).items():
        if record["how"] is None:
            console.print(f"{rid}: not placed ({record['reason'] or 'it never scanned'}); "
                          f"{record['scans_before']} scans and {record['odometry_before']} odometry messages held")
        elif record["how"] != "start pose":
            met = f", {record['meetings']} meetings with placed robots" if record.get("meetings") else ""
            console.print(f"{rid}: placed by {record['how']} at {record['placed_s']:.1f} s "
                          f"({record.get('placed_after_first_scan_s', 0.0):.1f} s after its first scan; "
                          f"{record['scans_before']} scans held before{met})")
    fleet = output.get("fleet_aligned") or {}
    map_rmse, landmarks, frame = output["map_rmse_m"], output["landmarks"], ""
    if fleet and output.get("start_poses") != "known":
        errors = ", ".join(f"{rid} {fmt(v)}" for rid, v in fleet["ate_rmse_m"].items())
        console.print(f"ATE after one SE(2) transform for the whole fleet: {errors} m")
        if "landmarks" in fleet:  # the map in the anchor's frame: judged after the same transform
            map_rmse, landmarks, frame = fleet.get("map_rmse_m"), fleet["landmarks"], " (after that transform)"
    elif aligned := output.get("map_aligned"):  # no robot truth: the map alone fitted to the survey
        map_rmse, landmarks = aligned["map_rmse_m"], aligned["landmarks"]
        frame = (f" (after one SE(2) transform of the map to the survey, no robot truth; {aligned['within_inlier']} "
                 f"surveyed landmarks within {aligned['inlier_m']:g} m)")
    marks = {k: "-" if v is None else v for k, v in (landmarks or {}).items()} or {
        k: "-" for k in ("estimated", "matched", "missed", "spurious")}
    console.print(f"map{frame} RMSE {fmt(map_rmse)} m; landmarks estimated {marks['estimated']}, matched "
                  f"{marks['matched']}, missed {marks['missed']}, spurious {marks['spurious']}"
                  + (f"; GPS RMSE (aligned) {fmt(output['gps_rmse_m'])} m" if output.get("gps_rmse_m") is not None else ""))


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_settings_arguments(parser, RunSettings)


def main(args: argparse.Namespace) -> int:
    settings = settings_from_args(RunSettings, args)
    from schemas.transport import Shutdown  # the signal flag every command uses (no session is opened)

    console = Console()
    stop = Shutdown(notice="stopping after the current event; what was computed is scored and saved",
                    second_interrupts=True)
    try:
        output = run(settings, should_stop=stop.is_set)
    except SettingsError:
        raise  # the CLI prints it as one line
    except (ValueError, FileNotFoundError) as exc:
        log.error("cannot run: %s", exc)
        return 2
    finally:
        stop.restore()
    print_results(output, console)
    if settings.json_out:
        console.print(f"results in {settings.json_out}")
    if settings.out:
        console.print(f"results, metrics, TUM trajectories and plots in {settings.out}/")
    if output.get("interrupted"):
        console.print(f"interrupted after {output['data_s']:.1f} s of data: the figures above cover that part only")
        return 130
    return 0
