"""kinfly-ground's outputs at the end of a run, a replay or on request: every vehicle's files
(mesh, trajectories, the ATE plot), summary.json, and the summary printed at exit (docs/ground.md,
"Outputs")."""
from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Any

from . import __version__
from ._native import LinkQuality, write_ply
from .merge import SharedWorlds
from .outputs import (ate_figures, evaluate, memory, write_atomically, write_error_plot,
                      write_json, write_tum)
from .station import Station
from .submaps import Mesh, joined_meshes
from .vehicle import Segment, VehicleState, percentile


def stats(values: list[float]) -> dict[str, float | int | None]:
    return {"count": len(values), "median": percentile(values, 50), "p90": percentile(values, 90),
            "p99": percentile(values, 99), "max": max(values) if values else None}


def format_ms(value: float | None) -> str:
    return "-" if value is None else f"{value:.1f}"


def _ate_summary(segment: Segment, truth: list | None, out: Path) -> dict[str, Any]:
    truth = truth if truth is not None else segment.ground_truth
    if not truth:
        return {"available": False, "reason": "no ground truth"}
    # Made at the end by Station.show_final; an export on request evaluates the map so far.
    results = segment.evaluation
    if results is None:
        trajectories = {"onboard": segment.onboard, "corrected": segment.corrected}
        if segment.chain is not None:
            trajectories["optimised"] = segment.chain.trajectory()
        results = evaluate(trajectories, truth)
    if not results:
        return {"available": False, "reason": "fewer than 3 poses match the ground truth in time"}
    write_error_plot(out / "ate.png", results)
    summary: dict[str, Any] = {"available": True, "plot": "ate.png"}
    for name, r in results.items():
        summary[name] = ate_figures(r)
    return summary


def _export_segment(segment: Segment, out: Path,
                    truth: list | None) -> tuple[dict[str, Any], Mesh | None]:
    """Writes the segment's files: their summary, and the mesh written (None without a map)."""
    files: dict[str, str] = {}
    result: dict[str, Any] = {"files": files, "corrected_poses": len(segment.corrected)}
    chain = segment.chain
    mesh = None
    if chain is not None:
        mesh = segment.final_mesh or chain.mesh()
        result["mesh_triangles"] = write_atomically(out / "mesh.ply",
                                                    lambda tmp: write_ply(str(tmp), *mesh))
        files["mesh"] = "mesh.ply"
        result["map_blocks"] = chain.num_blocks
        result["map_memory_mb"] = chain.memory_bytes / 1e6
        result["submaps"] = len(chain.submaps)
        write_tum(out / "trajectory_optimised.tum", chain.trajectory())
        files["trajectory_optimised"] = "trajectory_optimised.tum"
    write_tum(out / "trajectory_onboard.tum", segment.onboard)
    write_tum(out / "trajectory_corrected.tum", segment.corrected)
    files["trajectory_onboard"] = "trajectory_onboard.tum"
    files["trajectory_corrected"] = "trajectory_corrected.tum"
    if segment.ground_truth:
        write_tum(out / "trajectory_ground_truth.tum", segment.ground_truth)
        files["trajectory_ground_truth"] = "trajectory_ground_truth.tum"
    result["ate"] = _ate_summary(segment, truth, out)
    if result["ate"]["available"]:
        files["ate_plot"] = "ate.png"
    return result, mesh


def _vehicle_summary(state: VehicleState, link: LinkQuality | None, out: Path,
                     truth: list | None,
                     worlds: SharedWorlds) -> tuple[dict[str, Any], Mesh | None]:
    """The vehicle's summary, its files written, and its current map's mesh."""
    with state.lock:
        segment, finished = state.segment, list(state.finished_segments)

    def world(number: int) -> dict[str, Any]:
        # The world the map of its NUMBERth odometry frame is in: its own, or that of the map
        # it was merged with (merge.py), a vehicle's map of one of its odometry frames (0: its
        # first); T_world_map places its own optimised world there.
        vehicle_id, segment = worlds.world_of((state.vehicle_id, number))
        return {"vehicle_id": vehicle_id, "segment": segment,
                "T_world_map": worlds.T_world_map((state.vehicle_id, number)).tolist()}

    summary: dict[str, Any] = {
        "vehicle_id": state.vehicle_id,
        "keyframes": dataclasses.asdict(state.counters),
        "latency_ms": stats(state.latencies_ms),
        "refine_ms": stats(state.refine_ms),
        "reset_counter": state.reset_counter,
        # This session's first: a station started after the drone (restarted) never saw those
        # before it.
        "first_keyframe_id": min(state.session_keyframe_ids, default=None),
        # The onboard and corrected trajectories stay in the map's own world; the optimised
        # one and the mesh are in this one.
        "world": world(len(finished)),
    }
    files, mesh = _export_segment(segment, out, truth)
    summary.update(files)
    # Earlier odometry frames (before a drone restart), each complete on its own.
    summary["earlier_segments"] = [
        {"directory": f"segments/{i}", "world": world(i - 1),
         **_export_segment(s, out / "segments" / str(i), None)[0]}
        for i, s in enumerate(finished, 1)]
    if link is not None:
        summary["link"] = link_summary(link)
    d = state.drone_status
    if d is not None:
        summary["drone_reported"] = {
            "final": d.final,
            "frames_captured": d.frames_captured, "queue_drops": d.queue_drops,
            "frames_lost": d.frames_lost, "keyframes_sent": d.keyframes_sent,
            "last_keyframe_id": d.last_keyframe_id, "keyframes_dropped": d.keyframes_dropped,
            "send_budget_bps": d.send_budget_bps, "redundancy": d.redundancy,
            "keyframe_scale": d.keyframe_scale, "keyframes_skipped": d.keyframes_skipped,
            "chunks_sent": d.chunks_sent, "chunks_resent": d.chunks_resent,
            "corrections_accepted": d.corrections_accepted,
            "rejected_wrong_key": d.rejected_wrong_key, "rejected_bad_mac": d.rejected_bad_mac}
    return summary, mesh


def link_summary(link: LinkQuality) -> dict[str, Any]:
    """The keyframe link's figures (Receiver.link_quality) for summary.json: the ground's status
    fields, and the chunks by outcome."""
    c = link.chunks
    return {
        "loss": link.link_loss, "loss_run": link.link_loss_run,
        "goodput_bps": link.goodput_bps, "queue_delay_ms": link.queue_delay_ms,
        "redundancy": link.redundancy, "keyframe_age_ms": link.keyframe_age_ms,
        "chunks_received": link.chunks_received,
        "keyframes_completed": c.keyframes_completed,
        "keyframes_recovered": link.keyframes_recovered,
        "keyframes_repaired": link.keyframes_repaired,
        "keyframes_incomplete": link.keyframes_incomplete,
        "repair_requests": link.repair_requests,
        "chunks": {name: getattr(c, name) for name in (
            "stored", "duplicate", "surplus", "stale", "mismatch", "oversized", "malformed",
            "digest_mismatch", "restarts")},
    }


def format_link(link: dict[str, Any] | None, drone: dict[str, Any] | None) -> str:
    """One line of the link's quality (summary.json's "link") and how the drone sends (its
    budget, redundancy, image scale, keyframes skipped); each only once chunks went over it (a
    drone that sends whole keyframes has none of these figures)."""
    parts = []
    if link is not None and link["chunks_received"] > 0:
        parts.append(f"link: {100.0 * link['loss']:.1f}% chunks lost (runs of "
                     f"{link['loss_run']:.1f}), {link['goodput_bps'] * 1e-6:.2f} Mbit/s, "
                     f"{link['repair_requests']} repairs asked, {link['keyframes_recovered']} "
                     f"keyframes recovered, {link['keyframes_incomplete']} incomplete")
    if drone is not None and drone["chunks_sent"] > 0:
        parts.append(f"drone: budget {drone['send_budget_bps'] * 1e-6:.2f} Mbit/s, redundancy "
                     f"{drone['redundancy']:.2f}, scale 1/{drone['keyframe_scale']}, "
                     f"{drone['keyframes_skipped']} keyframes skipped")
    return "; ".join(parts)


def export(station: Station, out: Path, mode: str, started: float, truth: list | None,
           extra: dict[str, Any]) -> dict[str, Any]:
    """Writes every vehicle's outputs and summary.json (last). Runs on the fusion thread or after
    it stopped, so the maps hold still."""
    # A summary from an earlier export must not vouch for files this one is replacing.
    (out / "summary.json").unlink(missing_ok=True)
    vehicles, meshes = {}, {}
    for vid, state in sorted(list(station.vehicles.items())):
        where = out if station.vehicle_id is not None else out / f"vehicle_{vid}"
        link = station.receiver.link_quality(vid)
        vehicle, mesh = _vehicle_summary(state, link, where, truth, station.mapper.worlds)
        vehicles[str(vid)] = {"directory": str(where), **vehicle}
        if mesh is not None:
            meshes[vid] = mesh
    received = station.receiver.rejects  # what the ground can reject (the rest are the drone's)
    rejects = {"malformed": received.malformed, "unknown_channel": received.unknown_channel,
               "wrong_vehicle": received.wrong_vehicle}
    rejects["too_many_vehicles"] = station.rejected_too_many_vehicles
    rejects["too_many_link_vehicles"] = station.receiver.link_vehicles_refused
    rejects["handler_errors"] = station.handler_errors
    summary = {
        "kinfly_ground": __version__, "mode": mode, "duration_s": time.monotonic() - started,
        "vehicles": vehicles, "shared_maps": _export_shared_maps(vehicles, meshes, out),
        "rejected_messages": rejects, "memory": memory(),
        "params": dataclasses.asdict(station.params), **extra,
    }
    write_json(out / "summary.json", summary)
    return summary


def _export_shared_maps(vehicles: dict[str, Any], meshes: dict[int, Mesh],
                        out: Path) -> list[dict[str, Any]]:
    """Each world that several vehicles' current maps share (merge.py), as one mesh in
    shared_<its vehicle>/mesh.ply (shared_<vehicle>_<segment> where the world is that of a
    vehicle's later odometry frame): their meshes are in that world already."""
    groups: dict[tuple[int, int], list[int]] = {}
    for vid, v in vehicles.items():
        if int(vid) in meshes:
            groups.setdefault((v["world"]["vehicle_id"], v["world"]["segment"]),
                              []).append(int(vid))
    shared = []
    for (world, segment), members in sorted(groups.items()):
        if len(members) < 2:
            continue
        mesh = joined_meshes([meshes[vid] for vid in members])
        path = out / f"shared_{world}{f'_{segment}' if segment else ''}" / "mesh.ply"
        triangles = write_atomically(path, lambda tmp: write_ply(str(tmp), *mesh))
        shared.append({"world": world, "segment": segment, "vehicles": members,
                       "mesh": str(path), "mesh_triangles": triangles})
    return shared


def print_summary(summary: dict[str, Any], out: Path, rrd: Path | None) -> None:
    print(f"kinfly-ground {summary['mode']}: {summary['duration_s']:.1f} s, outputs in {out}")
    if not summary["vehicles"]:
        print("  no keyframes were received")
    for vid, v in summary["vehicles"].items():
        k, lat = v["keyframes"], v["latency_ms"]
        drone = v.get("drone_reported")
        if drone is None:
            print(f"  vehicle {vid}: no status heard from the drone")
        else:
            print(f"  vehicle {vid}: the drone sent {drone['keyframes_sent']} keyframes"
                  f"{'' if drone['final'] else ' by its last status heard (not its final one)'}"
                  f"; it dropped {drone['queue_drops']} of {drone['frames_captured']} frames "
                  f"(odometry behind) and {drone['keyframes_dropped']} keyframes (link busy)")
        print(f"    {k['keyframes_received']} keyframes received, {k['lost_on_link']} lost on "
              f"the link, {k['keyframes_fused']} fused, {k['keyframes_lost']} not refined, "
              f"{k['keyframes_dropped']} dropped from the queue, {k['corrections_sent']} "
              "corrections sent")
        print(f"    correction latency: median {format_ms(lat['median'])} ms, "
              f"p99 {format_ms(lat['p99'])} ms")
        if line := format_link(v.get("link"), drone):
            print(f"    {line}")
        # The counters are the vehicle's, over every odometry frame (segment) it flew: so are
        # the submaps counted here. More submaps than segments: some map was split.
        segments = len(v["earlier_segments"]) + 1
        submaps = v.get("submaps", 0) + sum(s.get("submaps", 0) for s in v["earlier_segments"])
        if submaps > segments:
            verdicts = (k['loops_accepted'], k['loops_refused_by_check'],
                        k['loops_refused_by_graph'], k['loop_checks_failed'])
            unchecked = k['loop_candidates'] - sum(verdicts)
            print(f"    {submaps} submaps"
                  + (f" in {segments} odometry frames" if segments > 1 else "")
                  + f" ({k['submaps_after_loss']} begun after lost "
                  f"keyframes); {k['loop_candidates']} loop candidates: {verdicts[0]} "
                  f"accepted, {verdicts[1]} refused by the check, {verdicts[2]} by the graph, "
                  f"{verdicts[3]} checks failed"
                  + (f", {unchecked} not checked before the end" if unchecked else ""))
        if k["merge_checks"] or k["merges"]:
            world = (v["world"]["vehicle_id"], v["world"]["segment"])
            own = (int(vid), len(v["earlier_segments"]))
            print(f"    {k['merge_checks']} checks for a common place with another vehicle's "
                  f"map: {k['merges']} found, {k['merges_refused']} not, "
                  f"{k['merge_checks_failed']} failed; "
                  + ("its map is in its own world" if world == own else
                     f"its map is in vehicle {world[0]}'s world"
                     + (f" (its odometry frame {world[1]})" if world[1] else "")))
        a = v["ate"]
        if a["available"]:
            parts = [f"{n} {a[n]['rmse_m'] * 100:.2f} cm ({a[n]['matched_poses']} poses)"
                     for n in ("onboard", "corrected", "optimised") if n in a]
            print("    ATE RMSE: " + ", ".join(parts))
        else:
            print(f"    ATE: {a['reason']}")
        print(f"    files: {', '.join(str(Path(v['directory']) / f) for f in v['files'].values())}")
    for shared in summary.get("shared_maps", []):
        print(f"  one map of vehicles {', '.join(map(str, shared['vehicles']))} in vehicle "
              f"{shared['world']}'s world"
              + (f" (its odometry frame {shared['segment']})" if shared["segment"] else "")
              + f": {shared['mesh']}")
    m = summary["memory"]
    after = summary.get("memory_after_fusion")
    print(f"  memory: {after['rss_mb']:.0f} MB resident after fusing, " if after else "  memory: ",
          end="")
    print(f"{m['rss_mb']:.0f} MB at exit, {m['peak_rss_mb']:.0f} MB peak")
    if rrd is not None:
        print(f"  rerun recording: {rrd} (open with: rerun {rrd})")
    print(f"  summary: {out / 'summary.json'}")
