#!/usr/bin/env python3
"""`make test` again and again beside other work (issue 12's figure: 3 of 3 green with both
cores busy).

    .venv/bin/python tests/bench/make_test_runs.py [--runs 3] [--busy 2] [--out out/bench]

Runs `make unit-test python-test` (the build and the packages must be in place: `make
test` once first) RUNS times with BUSY processes each keeping a core busy (tests/tools/busy.py),
once the load average shows them. Prints one line per run and one JSON object (also written to
OUT/make_test_runs.json): each run's exit status, time, load average and pytest's last line. A
benchmark: it reports, it does not fail on a figure.
"""
from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import time
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO_ROOT / "tests" / "tools"))
sys.path.insert(0, str(REPO_ROOT / "tests" / "bench"))
from busy import busy_cores  # noqa: E402
from demo_runs import settle_load  # noqa: E402

RUN_TIMEOUT_S = 3600


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--runs", type=int, default=3)
    p.add_argument("--busy", type=int, default=2, metavar="N",
                   help="processes keeping a core busy beside the tests (default 2)")
    p.add_argument("--out", type=Path, default=REPO_ROOT / "out" / "bench")
    args = p.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    runs = []
    with busy_cores(args.busy):
        settle_load(args.busy)
        for i in range(args.runs):
            started = time.monotonic()
            result = subprocess.run(["make", "-C", REPO_ROOT, "unit-test", "python-test"],
                                    capture_output=True, text=True, timeout=RUN_TIMEOUT_S)
            summaries = re.findall(r"^=+ (.*(?:passed|failed|error).*) =+$", result.stdout,
                                   re.MULTILINE)
            runs.append({"exit": result.returncode, "seconds": time.monotonic() - started,
                         "load_average_1min": os.getloadavg()[0],
                         "ctest": re.findall(r"\d+% tests passed.*", result.stdout)[-1:],
                         "pytest": summaries[-1:]})
            print(f"make_test_runs {i + 1}/{args.runs}: {json.dumps(runs[-1])}", file=sys.stderr,
                  flush=True)
    report = {"runs": len(runs), "busy_processes": args.busy,
              "green": sum(r["exit"] == 0 for r in runs), "each": runs}
    text = json.dumps(report, indent=2)
    (args.out / "make_test_runs.json").write_text(text + "\n")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
