"""Each kind of hostile and buggy input of issue 16 against its own live fleet, over seeds: the Targets' figures.

For every probe of benchmarks/support/abuse.py (``--probes``, default all) and every seed, one fleet: a router
and two copies of two simulated robots (three for the forged announcement of r3), central FastSLAM, D-SLAM and
MCL tracking every robot (and the association service for the query probe), ``ref`` untouched and ``hit``
attacked once, at robot time ``--attack-at``, by that probe alone, with the issue's sizes by default (200 robot
ids, 200 scans of 10^6 detections, JCBB 200 × 200, a LocalizeRequest of 3,000 detections × 50,000 particles).
Services run with their default settings (messages of unannounced ids wait 30 s before they go, counted;
``--unannounced-s`` shortens it).

Prints JSON: per probe, over the seeds (median and worst): crashes (services not running at the end, exiting
non-zero, logging a traceback or counting ``handler_error``); messages sent and counted under the probe's reasons
by each stream service; every reason counted in the window; reasons counted beyond the probe's (real messages
refused); each robot's error per service against the simulator's truth (final pose, mean over the last 3 s, mean
and median after the attack; the Target is checked on the median) for ``hit`` and ``ref`` and their difference
(hit − ref, metres); the RSS growth of each service (MB); each service's longest silence beyond the untouched
copy's (stats and poses, s); the queries' answer times; and per Target whether every run met it. Every run's
record follows. Variables FLEETSLAM_* of the caller are not passed on.

    .venv/bin/python benchmarks/abuse.py --seeds 3 --out reports/abuse.json
    .venv/bin/python benchmarks/abuse.py --probes seq_jump,ghost_big_scans --seeds 1
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from benchmarks.support.abuse import (ASSERTED, BLOCK_LIMIT_S, PROBES, RSS_LIMIT_MB, STREAM_SERVICES,  # noqa: E402
                                      TOLERANCE, Fleet, Plan, Scene, Step, estimates_off)
from report import emit, over_seeds  # noqa: E402

TARGETS = {  # the robot each probe aims at (none: the others must not notice)
    "seq_jump": ("r1",), "stamp_jump": ("r1",), "dt_lie": ("r2",), "forged_stream": ("r2",),
    "info_before_start": ("r3",), "info_joined": ("r1",), "stale_big_scans": ("r1",), "twin_robot": ("r2",),
    "buggy_seq_jump": ("r2",), "buggy_stamp_jump": ("r2",), "buggy_dt_lie": ("r2",), "buggy_control_lie": ("r2",),
}
MEASURES = ("final", "end", "after", "after_median")  # the errors Fleet._errors gives (ASSERTED is one)
AFTER_S = 16.0  # robot seconds of the fleet after the attack's window (the after-attack errors)


def budget_s(name: str, scene: Scene, unannounced_s: float) -> float:
    """Wall seconds the attack of probe ``name`` may take to be sent and counted."""
    if name in ("ghosts", "ghost_big_scans"):
        return unannounced_s + 15.0 + scene.big_scans * 0.1
    if name == "stale_big_scans":
        return 20.0 + scene.big_scans * 0.1
    if name == "heavy_queries":
        return scene.query_timeout_s + 5.0
    return 12.0


def plan_for(name: str, scene: Scene, attack_at: float, unannounced_s: float, service_env: tuple) -> Plan:
    probe = PROBES[name]
    targets = TARGETS.get(name, ())
    robots = ("r1", "r2", "r3") if "r3" in targets else ("r1", "r2")
    duration = attack_at + scene.speedup * budget_s(name, scene, unannounced_s) + AFTER_S
    step = Step(probe, targets, None if probe.before_robots else attack_at)
    return Plan(robots=robots, duration=round(duration), steps=(step,), assoc=probe.query, attack_s=AFTER_S,
                service_env=service_env)


def run_one(name: str, scene: Scene, args, workdir: Path) -> dict:
    """One fleet attacked by probe ``name``: its record, flattened for the summary."""
    unannounced_s = 30.0 if args.unannounced_s is None else args.unannounced_s
    env = () if args.unannounced_s is None else (("FLEETSLAM_UNANNOUNCED_S", str(args.unannounced_s)),)
    plan = plan_for(name, scene, args.attack_at, unannounced_s, env)
    try:
        result = Fleet(plan, scene, workdir).run()
    except Exception as exc:  # noqa: BLE001 - one run that could not be played is a record, not the end
        return {"seed": scene.seed, "error": f"{type(exc).__name__}: {exc}"}
    step, final = result["steps"][name], result["final"]
    sent = step["sent"].get("messages", 0)
    crashes = (sum(not alive for alive in final["alive"].values())
               + sum(code != 0 for code in final["exit_codes"].values())
               + sum(final["tracebacks"].values())
               + sum(rejected.get("handler_error", 0) for rejected in final["rejected"].values()))
    errors = {key: row for key, row in final["errors"].items() if not key.startswith("_")}
    row = {"seed": scene.seed, "wall_s": result["wall_s"], "crashes": crashes, "sent": sent,
           "counted": step["counted"], "rejected": step["rejected"]["hit"], "unexpected": step["unexpected"],
           "errors": errors, "after_window_s": final["errors"]["_after_window_s"],
           "rss_growth_mb": step["rss_growth_mb"], "absurd": final["absurd"], "notes": result["notes"],
           "blocked_s": {service: max(gaps.values(), default=0.0) for service, gaps in step["blocked_s"].items()},
           "queries": step["sent"].get("queries", {}), "lag_s": {k: v for k, v in final["stamp_lag_s"].items()
                                                                 if k.endswith("/hit") and v > 1e-6}}
    probe = PROBES[name]
    row["targets"] = {
        "no_crash": crashes == 0 and not any(final["absurd"].values()),
        "counted": probe.query or (sent > 0 and all(n >= sent for n in step["counted"].values())
                                   and not step["unexpected"]),
        "estimates_within": not estimates_off(final["errors"]) and not row["lag_s"],
        **({"rss_under_100_mb": all(mb < RSS_LIMIT_MB for mb in step["rss_growth_mb"].values())} if probe.flood
           else {}),
        "blocks_under_1_s": all(gap <= BLOCK_LIMIT_S for gap in row["blocked_s"].values()),
        **({"queries_answered": all(q.get("answer_s") is not None for q in row["queries"].values())}
           if probe.query else {}),
    }
    return row


def summarize(runs: list[dict]) -> dict:
    """Over the seeds: median and worst of each figure, and whether every run met each Target."""
    played = [run for run in runs if "error" not in run]
    out: dict = {"runs": len(runs), "failed_to_play": [run for run in runs if "error" in run]}
    if not played:
        return out
    out.update(over_seeds(played, ("crashes", "sent", "wall_s", "after_window_s")))
    flat = []
    for run in played:
        row = {f"counted.{k}": v for k, v in run["counted"].items()}
        row.update({f"rss_growth_mb.{k}": v for k, v in run["rss_growth_mb"].items()})
        row.update({f"blocked_s.{k}": v for k, v in run["blocked_s"].items()})
        for key, errors in run["errors"].items():
            for name in [f"{copy}_{when}_m" for copy in ("ref", "hit") for when in MEASURES]:
                row[f"errors.{key}.{name}"] = errors.get(name)
            for when in MEASURES:
                hit, ref = errors.get(f"hit_{when}_m"), errors.get(f"ref_{when}_m")
                row[f"errors.{key}.{when}_hit_minus_ref_m"] = None if hit is None or ref is None else hit - ref
        for query, answer in run["queries"].items():
            row[f"queries.{query}.answer_s"] = answer.get("answer_s")
        flat.append(row)
    keys = sorted({key for row in flat for key in row})
    spread = over_seeds(flat, keys)
    for key, value in spread.items():
        node = out
        parts = key.split(".")
        for part in parts[:-1]:
            node = node.setdefault(part, {})
        node[parts[-1]] = value
    out["counted"] = {service: out.get("counted", {}).get(service) for service in STREAM_SERVICES}
    reasons = sorted({reason for run in played for rejected in run["rejected"].values() for reason in rejected})
    out["rejected_by_reason"] = {
        service: {reason: over_seeds([{"n": run["rejected"].get(service, {}).get(reason, 0)} for run in played],
                                     ("n",))["n"] for reason in reasons
                  if any(run["rejected"].get(service, {}).get(reason) for run in played)}
        for service in STREAM_SERVICES}
    out["unexpected"] = [{"seed": run["seed"], **run["unexpected"]} for run in played if run["unexpected"]]
    out["replies"] = [{"seed": run["seed"], **{q: a.get("reply") for q, a in run["queries"].items()}}
                      for run in played if run["queries"]]
    names = sorted({name for run in played for name in run["targets"]})
    out["targets_met"] = {name: all(run["targets"].get(name, True) for run in played) for name in names}
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--probes", default=",".join(PROBES), help="comma-separated probes (default: all)")
    parser.add_argument("--seeds", type=int, default=3, help="seeds per probe (about 1 min per run)")
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument("--speedup", type=float, default=2.0, help="robots' speed-up over real time")
    parser.add_argument("--attack-at", type=float, default=5.0, help="robot time (s) of the attack")
    parser.add_argument("--ghosts", type=int, default=200)
    parser.add_argument("--big-scans", type=int, default=200, help="scans of each big-scan flood")
    parser.add_argument("--big-ranges", type=int, default=10**6, help="detections per big scan")
    parser.add_argument("--jcbb-size", type=int, default=200)
    parser.add_argument("--localize-observations", type=int, default=3000)
    parser.add_argument("--localize-particles", type=int, default=50_000)
    parser.add_argument("--unannounced-s", type=float, help="FLEETSLAM_UNANNOUNCED_S of every service (default: "
                        "the services' own, 30 s)")
    parser.add_argument("--out", help="also write the JSON here")
    args = parser.parse_args()
    names = [name.strip() for name in args.probes.split(",") if name.strip()]
    unknown = [name for name in names if name not in PROBES]
    if unknown:
        parser.error(f"unknown probes {unknown}; known: {', '.join(PROBES)}")

    started = time.monotonic()
    result: dict = {"probes": {}, "seeds": list(range(args.first_seed, args.first_seed + args.seeds)),
                    "settings": {k: v for k, v in vars(args).items() if k not in ("out", "probes")},
                    "estimates_within": {"error": ASSERTED, "ratio": 1 + TOLERANCE[0], "floor_m": TOLERANCE[1]}}
    with tempfile.TemporaryDirectory(prefix="abuse-") as folder:
        for name in names:
            runs = []
            for seed in result["seeds"]:
                scene = Scene(seed=seed, speedup=args.speedup, ghosts=args.ghosts, big_scans=args.big_scans,
                              big_ranges=args.big_ranges, jcbb_size=args.jcbb_size,
                              localize_observations=args.localize_observations,
                              localize_particles=args.localize_particles)
                run = run_one(name, scene, args, Path(folder) / f"{name}-{seed}")
                runs.append(run)
                met = ", ".join(f"{k} {'ok' if v else 'NO'}" for k, v in run.get("targets", {}).items())
                print(f"{name} seed {seed}: {run.get('error') or met} ({run.get('wall_s')} s)", file=sys.stderr,
                      flush=True)
            result["probes"][name] = {"what": PROBES[name].what, "targets": list(TARGETS.get(name, ())),
                                      "expected": sorted(PROBES[name].expected), **summarize(runs), "per_run": runs}
    result["targets_met"] = {name: summary.get("targets_met", {}) for name, summary in result["probes"].items()}
    result["wall_s"] = round(time.monotonic() - started, 1)
    emit(result, args.out)


if __name__ == "__main__":
    main()
