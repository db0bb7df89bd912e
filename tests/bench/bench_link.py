#!/usr/bin/env python3
"""Keyframe delivery over LCM between two processes on loopback, in a private network namespace.

    .venv/bin/python tests/bench/bench_link.py [--data SHARED_DATA] [--seconds 20] [--out out/bench]

A 640x480 keyframe after compression is larger than one UDP datagram, so LCM fragments it; this
measures what arrives. For each rate (5 and 10 Hz) `kinfly-link-bench drone` sends the shared
TUM teddy frames for --seconds while `kinfly-link-bench ground` receives, decodes and checks them
bit for bit. Prints one JSON object: per rate, keyframes sent and received, loss, latency median
and p99 (receive time minus send time, one host clock), message size and the link bandwidth, next
to DESIGN.md's link budget (keyframes at >= 5 Hz within 10 Mbit/s). A benchmark: it reports and
never fails on the figures.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO_ROOT / "tests" / "tools"))
sys.path.insert(0, str(REPO_ROOT / "tests" / "eval"))
sys.path.insert(0, str(REPO_ROOT / "scripts"))  # netns.py, shared with make demo
import kinfly_eval  # noqa: E402
from netns import network_namespace  # noqa: E402

LINK_BUDGET_MBIT_S = 10.0
RATES_HZ = (5.0, 10.0)
VEHICLE = 1


def run_rate(prefix: list[str], bench: Path, tum: Path, rate_hz: float, seconds: float) -> dict:
    ground = subprocess.Popen(
        [*prefix, bench, "ground", "--vehicle", str(VEHICLE), "--tum", tum,
         "--seconds", str(seconds + 5)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert ground.stderr is not None
        for line in ground.stderr:
            if "listening" in line:
                break
        drone = subprocess.run(
            [*prefix, bench, "drone", "--vehicle", str(VEHICLE), "--tum", tum,
             "--rate", str(rate_hz), "--seconds", str(seconds)],
            check=True, capture_output=True, text=True)
        ground.terminate()  # SIGTERM: it prints its summary and exits
        ground_out, _ = ground.communicate(timeout=30)
    finally:
        ground.kill()
    sent = json.loads(drone.stdout)
    got = json.loads(ground_out)
    mbit_s = got["message_bytes_median"] * 8 * rate_hz / 1e6
    return {
        "sent": sent["sent"],
        "received": got["received"],
        "lost": sent["sent"] - got["received"],
        "loss_fraction": round((sent["sent"] - got["received"]) / max(sent["sent"], 1), 6),
        "latency_ms": got["latency_ms"],
        "message_bytes_median": got["message_bytes_median"],
        "bandwidth_mbit_s": round(mbit_s, 3),
        "within_link_budget": mbit_s <= LINK_BUDGET_MBIT_S,
        "bit_exact": got["bit_exact"],
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--bench", type=Path, default=REPO_ROOT / "build/bin/kinfly-link-bench")
    parser.add_argument("--data", type=Path, default=kinfly_eval.data_root(REPO_ROOT))
    parser.add_argument("--seconds", type=float, default=20.0, help="per rate")
    parser.add_argument("--out", type=Path, default=REPO_ROOT / "out" / "bench")
    args = parser.parse_args()

    tum = args.data / kinfly_eval.TUM_SEQUENCE_SUBDIR
    results: dict = {"sequence": str(tum), "seconds_per_rate": args.seconds,
                     "budget": {"rate_hz_min": 5.0, "bandwidth_mbit_s_max": LINK_BUDGET_MBIT_S}}
    with network_namespace("bench") as prefix:
        for rate in RATES_HZ:
            results[f"{rate:g}_hz"] = run_rate(prefix, args.bench, tum, rate, args.seconds)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "link.json").write_text(json.dumps(results, indent=2) + "\n")
    print(json.dumps(results, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
