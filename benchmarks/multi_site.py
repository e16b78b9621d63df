"""Three sites meshed over slow, lossy links, with faults: the scenario of tests/integration/sites.py, repeated.

Per run: the cut of site1's cable (``--cut-s``, 30 s by default: three leases), the restart of site2's router, then
every message each robot sent against what reached the depot (lost), how soon after its cable's return site1's
robot was heard at the depot, how soon after its router's restart site2's was, and the bytes per second each
site's cable carried with one robot at 10 Hz. Needs root (network namespaces); links are shaped with ``tc netem``
where the kernel has it (this machine's has not: the runs say so).

    sudo python benchmarks/multi_site.py --runs 10 --out reports/multi_site.json
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from benchmarks.report import emit, over_seeds, summary  # noqa: E402
from tests.integration.netns import NetnsLab, netns_unavailable  # noqa: E402
from tests.integration.sites import run_sites  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=10)
    parser.add_argument("--cut-s", type=float, default=30.0)
    parser.add_argument("--out", default=None)
    args = parser.parse_args()
    why = netns_unavailable()
    if why:
        sys.exit(f"multi_site: {why}")
    runs = []
    for index in range(args.runs):
        lab = NetnsLab(f"sites{index}")
        try:
            run = run_sites(lab, Path(tempfile.mkdtemp(prefix=f"multi-site-{index}-")), cut_s=args.cut_s)
        finally:
            lab.close()
        complete = all(run.received[rid][s] == list(range(n)) for rid, counts in run.sent.items()
                       for s, n in counts.items())
        row = {**run.figures, "complete_in_order": complete,
               "central_missing": None if run.central is None else run.central["extra"].get("missing"),
               "central_took_all": run.central is not None,
               "site1_bytes_per_s": run.figures["cable_bytes_per_s"]["site1"],
               "site2_bytes_per_s": run.figures["cable_bytes_per_s"]["site2"]}
        print(f"run {index}: {row}", file=sys.stderr)
        runs.append(row)
    keys = ["lost", "site1_heard_again_s", "site2_heard_again_s", "site1_bytes_per_s", "site2_bytes_per_s"]
    result = {"benchmark": "multi_site", "runs": len(runs), "cut_s": args.cut_s, "links": runs[0]["links"],
              "runs_with_nothing_lost": sum(r["lost"] == 0 and r["complete_in_order"] and r["central_took_all"]
                                            and r["central_missing"] == 0 for r in runs),
              "runs_heard_again_within_2_s": sum(r["site1_heard_again_s"] <= 2.0 for r in runs),
              **over_seeds(runs, keys), "per_run": runs}
    emit(summary(result), args.out)


if __name__ == "__main__":
    main()
