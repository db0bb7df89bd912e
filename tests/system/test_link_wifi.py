"""Keyframes in chunks over a Wi-Fi-like link (scripts/netns.py, LinkShape): the two ends of
kinfly-link-bench in a namespace whose `lo` loses packets, 60 keyframes at 10 Hz, each checked
bit for bit. tests/bench/bench_link.py measures the same link with 3000 keyframes a shape; this
is the short check that the path works.

The threshold, 95 % of keyframes, is far below what the link should do (the redundancy is chosen
for a modelled failure of 1e-3 a keyframe, so 60 keyframes lose none or one nearly always) on
purpose: on a loaded machine a receiving socket or LCM's queue may overflow while the ground's
thread waits for a core, which loses chunks beyond the link's loss; 3 keyframes of 60 leave
room for that, and a broken FEC or repair path (tens of keyframes lost at 5 % loss) still
fails. Both tests together take ~16 s, beside two busy loops too."""
from __future__ import annotations

import json
import subprocess
from collections.abc import Callable
from pathlib import Path

from netns import LinkShape, link_counters

from conftest import built, wait_for_line

VEHICLE = 3
KEYFRAMES = 60
RATE_HZ = 10.0
MIN_DELIVERED = 0.95
WifiNetns = Callable[[LinkShape], list[str]]


def send_keyframes(prefix: list[str], sample_dir: Path, shape: LinkShape, repair: bool) -> dict:
    """KEYFRAMES keyframes from the drone end to the ground end over the shaped link, the drone's
    redundancy set for the shape's loss (what the ground would report); both summaries."""
    bench = built("bin/kinfly-link-bench")
    flags = ["--repair"] if repair else []
    ground = subprocess.Popen(
        [*prefix, bench, "ground", "--vehicle", str(VEHICLE), "--tum", sample_dir,
         "--seconds", "40", *flags],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        wait_for_line(ground, "listening")
        drone = subprocess.run(
            [*prefix, bench, "drone", "--vehicle", str(VEHICLE), "--tum", sample_dir,
             "--rate", str(RATE_HZ), "--seconds", str((KEYFRAMES - 0.5) / RATE_HZ),
             "--loss", str(shape.loss), "--loss-run", str(shape.loss_run_packets), *flags],
            check=True, capture_output=True, text=True, timeout=60)
        # The ground ends by itself after the drone's final status (or 1 s without its status).
        try:
            ground_out, _ = ground.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            ground.kill()
            out, err = ground.communicate()
            # The link's counters tell a loss model stuck in its bad state (every packet
            # dropped) from a ground end that heard its packets and did not stop.
            raise AssertionError(f"the ground end did not stop after the drone's end "
                                 f"(drone: {drone.stdout.strip()}): stdout {out!r}, "
                                 f"stderr {err!r}; link counters "
                                 f"{link_counters(prefix)}") from None
    finally:
        ground.kill()
    return {"drone": json.loads(drone.stdout), "ground": json.loads(ground_out)}


def test_fec_delivers_keyframes_at_5_percent_loss(wifi_netns: WifiNetns,
                                                  sample_dir: Path) -> None:
    shape = LinkShape(loss=0.05)
    run = send_keyframes(wifi_netns(shape), sample_dir, shape, repair=False)
    drone, ground = run["drone"], run["ground"]
    # A loaded machine may make the drone skip a frame (its last keyframe still going out).
    assert drone["sent"] >= 0.8 * KEYFRAMES, drone
    assert ground["drone_sent"] == drone["sent"]  # the drone's final status was heard
    assert ground["received"] >= MIN_DELIVERED * drone["sent"], ground
    assert ground["bit_exact"] is True
    # FEC did the work: with 36 originals a keyframe has all of them only 0.95^36 = 16 % of the
    # time (50 of 60 expected to need recovery chunks, sigma 3).
    assert ground["keyframes"]["recovered_by_fec"] >= KEYFRAMES // 2, ground
    assert ground["repair_requests"] == 0 and drone["resent"] == 0
    assert ground["link_loss"]["fraction"] > 0


def test_fec_and_repair_deliver_keyframes_through_bursts(wifi_netns: WifiNetns,
                                                         sample_dir: Path) -> None:
    shape = LinkShape(loss=0.05, loss_run_packets=5)
    run = send_keyframes(wifi_netns(shape), sample_dir, shape, repair=True)
    drone, ground = run["drone"], run["ground"]
    assert ground["received"] >= MIN_DELIVERED * drone["sent"], ground
    assert ground["bit_exact"] is True
    # Redundancy for bursts (m = 32 of 36) leaves little to repair; what was, was asked for.
    assert ground["keyframes"]["repaired"] <= ground["repair_requests"]
