"""The soak run (tests/system/soak.py, `make soak` flies it for an hour), two minutes of it: the
shipped flight bounced through kinfly-fw and kinfly-ground in a network namespace, memory sampled
on both ends. The script's own criteria decide; this checks that it ran them and that its report
says what it measured."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[2]
SOAK = REPO_ROOT / "tests" / "system" / "soak.py"
MINUTES = 2
# Two minutes of flight; the ground's start (rerun, evo imports) and exit, and a loaded machine.
TIMEOUT_S = MINUTES * 60 + 300


def test_two_minute_soak_holds(tmp_path: Path) -> None:
    out = tmp_path / "soak"
    # Queue drops are reported, not failed: make test must hold beside busy loops (make
    # test-runs), where the drone's odometry falls behind and drops frames, counted, as designed.
    # Every other criterion holds: nothing dropped uncounted, memory flat, no stall.
    run = subprocess.run([sys.executable, SOAK, "--minutes", str(MINUTES), "--out", out,
                          "--allow-queue-drops"],
                         capture_output=True, text=True, timeout=TIMEOUT_S)
    if run.returncode != 0 and "network namespace" in run.stderr and not os.environ.get("CI"):
        pytest.skip(run.stderr)
    assert run.returncode == 0, run.stdout + run.stderr
    report = json.loads((out / "soak.json").read_text())
    assert report["ok"] and all(c["ok"] for c in report["criteria"]), report["criteria"]
    assert report["flight_s"] >= MINUTES * 60
    k = report["keyframes"]
    # A keyframe at least every second of flight (keyframe.max_interval_s), each accounted for
    # (the script's criteria), nearly all of them fused.
    assert k["sent"] >= MINUTES * 60 and k["fused"] >= 0.9 * k["sent"], k
    assert report["queue_drops_reported_only"]
    # Memory was followed all along: about a sample every second or more, both programs.
    samples = report["samples"]
    assert len(samples) >= MINUTES * 60 / report["sample_period_s"] * 0.9
    assert all(s["firmware_rss_mb"] > 0 and s["ground_rss_mb"] > 0 for s in samples)
    assert report["rss"]["firmware"]["growth_after_warm_up_mb"] <= 1.0
