#!/usr/bin/env python3
"""`make demo` again and again, quiet or beside other work (issue 12's figures).

    .venv/bin/python tests/bench/demo_runs.py [--runs 20] [--busy 0] [--out out/bench]

Each run is scripts/demo.py as `make demo` runs it (the shipped flight log through kinfly-fw and
kinfly-ground over LCM in a network namespace), with --busy N processes each keeping a core busy
beside it (tests/tools/busy.py). A run counts as good when the demo exits 0, which it does only
when every keyframe the drone sent was fused, every output was written and the ATE computed.
Prints one line per run and one JSON object (also written to OUT/demo_runs_<quiet|busyN>.json):
the runs, how many were good, and the medians of the correction latency and the ATE, with the
load average over each run. A benchmark: it reports, it does not fail on a figure.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

REPO_ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO_ROOT / "tests" / "tools"))
from busy import busy_cores  # noqa: E402

DEMO = REPO_ROOT / "scripts" / "demo.py"
DEMO_TIMEOUT_S = 600
# The 1-minute load average reaches 95 % of a new steady load after 3 minutes.
LOAD_SETTLE_TIMEOUT_S = 240.0


def one_run(out: Path) -> dict[str, Any]:
    started = time.monotonic()
    result = subprocess.run([sys.executable, DEMO, "--out", out], capture_output=True, text=True,
                            timeout=DEMO_TIMEOUT_S)
    run: dict[str, Any] = {"exit": result.returncode, "seconds": time.monotonic() - started,
                           "load_average_1min": os.getloadavg()[0]}
    if result.returncode != 0:
        run["why"] = result.stderr.strip().splitlines()[-3:]
    summary_path = out / "summary.json"
    if summary_path.is_file():
        vehicle = json.loads(summary_path.read_text())["vehicles"].get("1")
        if vehicle is not None:
            k, drone = vehicle["keyframes"], vehicle.get("drone_reported") or {}
            ate = vehicle["ate"]
            run.update({
                "keyframes_sent": drone.get("keyframes_sent"),
                "keyframes_fused": k["keyframes_fused"],
                "lost_on_link": k["lost_on_link"],
                "dropped_by_ground_queue": k["keyframes_dropped"],
                "drone_queue_drops": drone.get("queue_drops"),
                "latency_ms_median": vehicle["latency_ms"]["median"],
                "latency_ms_p99": vehicle["latency_ms"]["p99"],
                "ate_onboard_m": ate["onboard"]["rmse_m"] if ate["available"] else None,
                "ate_corrected_m": ate["corrected"]["rmse_m"] if ate["available"] else None,
            })
    run["every_keyframe_fused"] = (run["exit"] == 0 and run.get("keyframes_sent") is not None
                                   and run["keyframes_fused"] == run["keyframes_sent"])
    return run


def settle_load(busy: int) -> None:
    """Until the 1-minute load average shows the BUSY processes (it lags them by about a
    minute), so that the first runs meet the same machine as the last and the load reported
    with each run is the one it met; at most LOAD_SETTLE_TIMEOUT_S."""
    deadline = time.monotonic() + LOAD_SETTLE_TIMEOUT_S
    while busy and os.getloadavg()[0] < busy and time.monotonic() < deadline:
        time.sleep(1.0)


def median(runs: list[dict[str, Any]], key: str) -> float | None:
    values = [r[key] for r in runs if r.get(key) is not None]
    return statistics.median(values) if values else None


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--runs", type=int, default=20)
    p.add_argument("--busy", type=int, default=0, metavar="N",
                   help="processes keeping a core busy beside the demo (default 0: quiet)")
    p.add_argument("--out", type=Path, default=REPO_ROOT / "out" / "bench")
    args = p.parse_args()
    mode = "quiet" if args.busy == 0 else f"busy{args.busy}"
    work = REPO_ROOT / "out" / "demo_runs" / mode
    args.out.mkdir(parents=True, exist_ok=True)
    runs = []
    with busy_cores(args.busy):
        settle_load(args.busy)
        for i in range(args.runs):
            runs.append(one_run(work / str(i)))
            r = runs[-1]
            print(f"demo_runs {mode} {i + 1}/{args.runs}: exit {r['exit']}, "
                  f"{r.get('keyframes_fused')} of {r.get('keyframes_sent')} keyframes fused, "
                  f"latency median {r.get('latency_ms_median')} ms, "
                  f"load {r['load_average_1min']:.1f}", file=sys.stderr, flush=True)
    result = {
        "mode": mode, "runs": len(runs), "busy_processes": args.busy,
        "good_runs": sum(r["exit"] == 0 for r in runs),
        "runs_with_every_keyframe_fused": sum(r["every_keyframe_fused"] for r in runs),
        "latency_ms_median": median(runs, "latency_ms_median"),
        "latency_ms_p99_median": median(runs, "latency_ms_p99"),
        "ate_corrected_m_median": median(runs, "ate_corrected_m"),
        "load_average_1min_median": median(runs, "load_average_1min"),
        "each": runs,
    }
    text = json.dumps(result, indent=2)
    (args.out / f"demo_runs_{mode}.json").write_text(text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
