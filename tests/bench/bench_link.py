#!/usr/bin/env python3
"""Keyframe delivery over LCM between two processes, in a private network namespace: on perfect
loopback at two rates, and over Wi-Fi-like links (scripts/netns.py, LinkShape).

    .venv/bin/python tests/bench/bench_link.py [--build build] [--data SHARED_DATA]
        [--seconds 20] [--shapes NAME...] [--rates HZ...] [--out out/bench]

`kinfly-link-bench drone` sends the shared TUM teddy frames for --seconds while
`kinfly-link-bench ground` receives, decodes and checks them bit for bit. Two tables:
- rates: perfect loopback (lo's 64 KB MTU) at 5 and 10 Hz: keyframes sent and received, loss,
  latency median and p99 (receive time minus send time, one host clock), message size and the
  link bandwidth, next to DESIGN.md's link budget (keyframes at >= 5 Hz within 10 Mbit/s);
- shapes: each link of LINK_SHAPES at 5 Hz: keyframes sent, received and lost, latency, and
  what the link did (packets seen and dropped by the loss model, the cap's queue drops, IP
  reassemblies that never completed), with, for independent loss, the keyframe loss expected
  if a keyframe is lost whenever one of its fragments is: 1 - (1 - loss)^fragments.
Writes both to --out/link.json, prints the JSON on stdout and the shapes table on stderr. A
benchmark: it reports and never fails on the figures.
"""
from __future__ import annotations

import argparse
import json
import math
import signal
import subprocess
import sys
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO_ROOT / "tests" / "tools"))
sys.path.insert(0, str(REPO_ROOT / "tests" / "eval"))
sys.path.insert(0, str(REPO_ROOT / "scripts"))  # netns.py, shared with make demo
import kinfly_eval  # noqa: E402
from netns import (LinkShape, as_root, link_counters, network_namespace,  # noqa: E402
                   send_signal, system_tool)

LINK_BUDGET_MBIT_S = 10.0
RATES_HZ = (5.0, 10.0)
VEHICLE = 1
# The links the keyframes cross, in one place: a new link (chunked keyframes, erasure coding,
# other channels) changes what kinfly-link-bench sends and receives, not this table.
LINK_SHAPES: dict[str, LinkShape] = {
    "loss_0": LinkShape(),
    "loss_1": LinkShape(loss=0.01),
    "loss_5": LinkShape(loss=0.05),
    "loss_10": LinkShape(loss=0.10),
    "loss_5_runs_5": LinkShape(loss=0.05, loss_run_packets=5),
    "cap_5mbit": LinkShape(rate_kbit_s=5000),
    "cap_2mbit": LinkShape(rate_kbit_s=2000),
}
SHAPE_RATE_HZ = 5.0
# IPv4 payload per fragment at MTU 1500 (1500 - 20, a multiple of 8), and what LCM and UDP add
# to a message (LCM's 8-byte header and the channel name, UDP's 8 bytes), roughly.
FRAGMENT_BYTES = 1480
DATAGRAM_OVERHEAD_BYTES = 8 + 20 + 8


def run_link(prefix: list[str], bench: Path, tum: Path, rate_hz: float, seconds: float) -> dict:
    """One drone -> ground run; both summaries merged."""
    ground = subprocess.Popen(
        [*prefix, bench, "ground", "--vehicle", str(VEHICLE), "--tum", tum,
         "--seconds", str(seconds + 5)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        assert ground.stderr is not None
        for line in ground.stderr:
            if "listening" in line:
                break
        drone = subprocess.run(
            [*prefix, bench, "drone", "--vehicle", str(VEHICLE), "--tum", tum,
             "--rate", str(rate_hz), "--seconds", str(seconds)],
            check=True, capture_output=True, text=True)
        send_signal(ground, signal.SIGTERM)  # it prints its summary and exits
        ground_out, _ = ground.communicate(timeout=30)
    finally:
        ground.kill()
    return {"drone": json.loads(drone.stdout), "ground": json.loads(ground_out)}


def run_rate(prefix: list[str], bench: Path, tum: Path, rate_hz: float, seconds: float) -> dict:
    run = run_link(prefix, bench, tum, rate_hz, seconds)
    sent, got = run["drone"], run["ground"]
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


def ip_counters(prefix: list[str]) -> dict[str, int]:
    """The namespace's IPv4 counters (/proc/net/snmp, Ip:)."""
    text = subprocess.run([*prefix, "cat", "/proc/net/snmp"], capture_output=True, text=True,
                          check=True).stdout
    names, values = [line.split()[1:] for line in text.splitlines() if line.startswith("Ip:")]
    return dict(zip(names, map(int, values)))


def qdisc_drops(prefix: list[str]) -> int:
    shown = subprocess.run([*as_root(prefix), system_tool("tc"), "-s", "-j", "qdisc", "show",
                            "dev", "lo"], capture_output=True, text=True, check=True).stdout
    return sum(q.get("drops", 0) for q in json.loads(shown))


def run_shape(shape: LinkShape, bench: Path, tum: Path, seconds: float) -> dict:
    with network_namespace("bench", shape) as prefix:
        run = run_link(prefix, bench, tum, SHAPE_RATE_HZ, seconds)
        link = link_counters(prefix)
        ip = ip_counters(prefix)
        queue_drops = qdisc_drops(prefix)
    sent, got = run["drone"]["sent"], run["ground"]["received"]
    row = {
        "link": shape.label(),
        "shape": {"mtu_bytes": shape.mtu_bytes, "loss": shape.loss,
                  "loss_run_packets": shape.loss_run_packets, "rate_kbit_s": shape.rate_kbit_s,
                  "queue_ms": shape.queue_ms},
        "rate_hz": SHAPE_RATE_HZ,
        "sent": sent,
        "received": got,
        "lost": sent - got,
        "loss_fraction": round((sent - got) / max(sent, 1), 4),
        "latency_ms": run["ground"]["latency_ms"] if got else None,
        "message_bytes_median": run["ground"]["message_bytes_median"] if got else None,
        "bit_exact": run["ground"]["bit_exact"],
        # At lo's ingress, by the loss model (none: no loss model).
        "packets_seen": link["seen"] if shape.loss else None,
        "packets_dropped": link["dropped"] if shape.loss else None,
        "burst_refused": link["burst_refused"] if shape.bursty else None,
        # Packets the cap's full queue refused: the rest of that datagram is never sent.
        "queue_drops": queue_drops if shape.rate_kbit_s is not None else None,
        # Fragments the receiving stack gave up on: incomplete datagrams timed out (after 30 s)
        # or refused because incomplete ones fill the reassembly memory (4 MB).
        "reassembly_failed": ip.get("ReasmFails", 0),
        "reassembly_timeouts": ip.get("ReasmTimeout", 0),
    }
    if got and shape.loss and not shape.bursty:
        fragments = math.ceil((row["message_bytes_median"] + DATAGRAM_OVERHEAD_BYTES)
                              / FRAGMENT_BYTES)
        row["independent_prediction"] = round(1 - (1 - shape.loss) ** fragments, 4)
    return row


def shapes_table(rows: dict[str, dict]) -> str:
    lines = ["| link | keyframes sent | received | lost | latency median / p99 ms |",
             "|---|---|---|---|---|"]
    for row in rows.values():
        latency = (f"{row['latency_ms']['median']:.1f} / {row['latency_ms']['p99']:.1f}"
                   if row["latency_ms"] else "-")
        predicted = (f" (independent: {row['independent_prediction'] * 100:.0f} %)"
                     if "independent_prediction" in row else "")
        lines.append(f"| {row['link']} | {row['sent']} | {row['received']} | "
                     f"{row['loss_fraction'] * 100:.1f} %{predicted} | {latency} |")
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--build", type=Path, default=REPO_ROOT / "build",
                        help="the build folder whose bin/kinfly-link-bench runs")
    parser.add_argument("--bench", type=Path, default=None,
                        help="kinfly-link-bench itself (default: BUILD/bin/kinfly-link-bench)")
    parser.add_argument("--data", type=Path, default=kinfly_eval.data_root(REPO_ROOT))
    parser.add_argument("--seconds", type=float, default=20.0, help="per rate and per shape")
    parser.add_argument("--rates", type=float, nargs="*", default=list(RATES_HZ),
                        help="keyframe rates on perfect loopback (none: skip that table)")
    parser.add_argument("--shapes", nargs="*", default=list(LINK_SHAPES),
                        choices=list(LINK_SHAPES), help="links to run (none: skip that table)")
    parser.add_argument("--out", type=Path, default=REPO_ROOT / "out" / "bench")
    args = parser.parse_args()
    bench = args.bench or args.build / "bin" / "kinfly-link-bench"
    if not bench.exists():
        parser.error(f"{bench} is not built (make build, or --build / --bench)")

    tum = args.data / kinfly_eval.TUM_SEQUENCE_SUBDIR
    results: dict = {"sequence": str(tum), "seconds_per_run": args.seconds,
                     "budget": {"rate_hz_min": 5.0, "bandwidth_mbit_s_max": LINK_BUDGET_MBIT_S},
                     "rates": {}, "shapes": {}}
    if args.rates:
        with network_namespace("bench") as prefix:
            for rate in args.rates:
                results["rates"][f"{rate:g}_hz"] = run_rate(prefix, bench, tum, rate,
                                                             args.seconds)
    for name in args.shapes:
        results["shapes"][name] = run_shape(LINK_SHAPES[name], bench, tum, args.seconds)
        print(f"[bench_link] {name}: {results['shapes'][name]['loss_fraction'] * 100:.1f} % "
              "of keyframes lost", file=sys.stderr)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "link.json").write_text(json.dumps(results, indent=2) + "\n")
    print(json.dumps(results, indent=2))
    if results["shapes"]:
        print(shapes_table(results["shapes"]), file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
