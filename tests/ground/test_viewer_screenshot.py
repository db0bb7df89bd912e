"""The viewer as a person sees it: a recording made through kinfly_ground.viewer is opened in the
real rerun viewer (the SDK's own binary, .venv/bin/rerun) on a virtual X display with software
Vulkan, and the pictures come from rerun's own screenshot call (an X screen grab of a Vulkan
window comes back blank). Checked: the picture is not blank; the views are the layout's (map,
camera, link and tracking plots; a tab per vehicle with several) and none reports an error; the
map is drawn, and it is by far the largest view on screen, measured by the pixel size of each
view's own screenshot.

Needs, on Debian 12: xvfb, libvulkan1 and mesa-vulkan-drivers, the X libraries libxcursor1, libxi6
and libxkbcommon-x11-0, and ca-certificates (see missing_packages). Without them the test is
skipped on a developer's machine and fails under CI (CI set), where a skip would hide that the
viewer was never looked at. The whole picture is left in the test's tmp_path as viewer.png."""
from __future__ import annotations

import contextlib
import ctypes.util
import glob
import io
import os
import select
import shutil
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TypeVar

import numpy as np
import pytest
import rerun as rr
from PIL import Image
from rerun.experimental import View, ViewerClient, ViewerState

from kinfly_ground.viewer import TIMELINE, Viewer

RERUN = Path(sys.executable).parent / "rerun"
SEED = 20261202
T0_US = 1_700_000_000_000_000
KEYFRAME_PERIOD_US = 200_000          # 5 Hz
KEYFRAMES = 10
HEIGHT, WIDTH = 120, 160
INTRINSICS = (133.0, 133.0, 79.5, 59.5)
DEPTH_SCALE_M = 1 / 5000
# A laptop's screen; the viewer's window fills it (no window manager under Xvfb).
SCREEN_WIDTH_PX, SCREEN_HEIGHT_PX = 1600, 900

# Timeouts are generous: the viewer renders on the CPU (lavapipe), on a loaded 2-core machine
# next to other tests. Each bounds a wait on a real event, never a guess at how long one takes.
XVFB_START_TIMEOUT_S = 60            # Xvfb writes its display number once it takes clients
VIEWER_START_TIMEOUT_S = 180         # the viewer's control port answers
LOAD_TIMEOUT_S = 180                 # the recording is loaded up to its last capture time
SCREENSHOT_TIMEOUT_S = 300           # the map has been painted with the recording in it
EXIT_TIMEOUT_S = 30                  # Xvfb or the viewer ends once told to
POLL_INTERVAL_S = 0.2                # between two questions to a process that is getting ready

# Not blank: rerun's dark UI with no data in it measures 9 grey levels of standard deviation, this
# recording's picture about 100; one colour everywhere is 0.
PICTURE_STD_MIN = 30.0
# The map is drawn: at least this share of its pixels differ from its background (the most
# common colour) by more than BACKGROUND_TOLERANCE. The wall mesh and depth cloud cover about a
# third of the view; an empty 3D view, its grid lines only, a few percent.
MAP_DRAWN_FRACTION_MIN = 0.10
BACKGROUND_TOLERANCE = 24            # [grey levels] per channel: antialiasing and shading noise
# The map's on-screen area against the next largest view's: the layout gives it two thirds of
# the width at full height, about four times the camera view; an even split of the width would
# give 2, the heuristic layout a thumbnail.
MAP_AREA_RATIO_MIN = 3.0

# The layout's views of one vehicle: (rerun view class, origin under the vehicle's prefix).
LAYOUT = {("3D", "world"), ("2D", "world/drone/camera"), ("TimeSeries", "health/link"),
          ("TimeSeries", "health/tracking")}

T = TypeVar("T")


def fail_or_skip(message: str) -> None:
    if os.environ.get("CI"):
        pytest.fail(message + "; CI must look at the viewer", pytrace=False)
    pytest.skip(message)


def missing_packages() -> list[str]:
    """The Debian packages of what the test needs that this machine lacks: Xvfb; Vulkan's loader
    and a driver; the X libraries the viewer loads at run time (without them it exits at once);
    CA certificates, which rerun's control client loads even to talk plain http to 127.0.0.1."""
    vulkan_drivers = [path for folder in ("/usr/share/vulkan/icd.d", "/etc/vulkan/icd.d",
                                          "/usr/local/share/vulkan/icd.d")
                      for path in glob.glob(f"{folder}/*.json")]
    present = {
        "xvfb": shutil.which("Xvfb") is not None,
        "libvulkan1": ctypes.util.find_library("vulkan") is not None,
        "mesa-vulkan-drivers": bool(vulkan_drivers or os.environ.get("VK_ICD_FILENAMES")
                                    or os.environ.get("VK_DRIVER_FILES")),
        "libxcursor1": ctypes.util.find_library("Xcursor") is not None,
        "libxi6": ctypes.util.find_library("Xi") is not None,
        "libxkbcommon-x11-0": ctypes.util.find_library("xkbcommon-x11") is not None,
        "ca-certificates": bool(Path("/etc/ssl/certs/ca-certificates.crt").exists()
                                or os.environ.get("SSL_CERT_FILE")),
    }
    return [package for package, found in present.items() if not found]


def wait_for(what: str, timeout_s: float, attempt: Callable[[], T | None]) -> T:
    """ATTEMPT's first result that is not None, asked again until TIMEOUT_S has passed."""
    deadline = time.monotonic() + timeout_s
    while True:
        result = attempt()
        if result is not None:
            return result
        if time.monotonic() > deadline:
            pytest.fail(f"timed out after {timeout_s:.0f} s waiting for {what}", pytrace=False)
        time.sleep(POLL_INTERVAL_S)


@pytest.fixture(scope="module")
def display(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """A virtual X display (Xvfb) of the laptop's size, on a display number it finds free."""
    if missing := missing_packages():
        fail_or_skip(f"the viewer test needs: apt-get install {' '.join(missing)}")
    log = tmp_path_factory.mktemp("xvfb") / "xvfb.log"
    with open(log, "wb") as log_file:
        # The display number comes on stdout (fd 1): a higher descriptor passed down does not
        # always survive the X server's start.
        xvfb = subprocess.Popen(
            ["Xvfb", "-displayfd", "1", "-nolisten", "tcp",
             "-screen", "0", f"{SCREEN_WIDTH_PX}x{SCREEN_HEIGHT_PX}x24"],
            stdout=subprocess.PIPE, stderr=log_file)
    try:
        # Xvfb writes the number when it is ready; an Xvfb that dies closes the pipe at once.
        readable, _, _ = select.select([xvfb.stdout], [], [], XVFB_START_TIMEOUT_S)
        number = os.read(xvfb.stdout.fileno(), 32).decode().strip() if readable else ""
        if not number:
            pytest.fail(f"Xvfb did not start: {log.read_text()[-2000:]}", pytrace=False)
        yield f":{number}"
    finally:
        xvfb.terminate()
        xvfb.wait(timeout=EXIT_TIMEOUT_S)
        xvfb.stdout.close()


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextlib.contextmanager
def running_viewer(display: str, log: Path) -> Iterator[ViewerClient]:
    """The rerun viewer in a window on DISPLAY, and a client to its control port. A fresh viewer
    per recording: a viewer keeps the first layout it showed for an application id."""
    port = free_port()
    env = {**os.environ, "DISPLAY": display,
           # As a person's laptop has it: the default backend, not a fallback to GL.
           "WGPU_BACKEND": "vulkan"}
    env.pop("WAYLAND_DISPLAY", None)
    with open(log, "wb") as log_file:
        # Its own process group: .venv/bin/rerun is a Python shim that runs the viewer binary as
        # its child, and both must go at the end.
        viewer = subprocess.Popen(
            [RERUN, "--port", str(port), "--hide-welcome-screen",
             "--window-size", f"{SCREEN_WIDTH_PX}x{SCREEN_HEIGHT_PX}"],
            env=env, stdout=log_file, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        url = f"rerun+http://127.0.0.1:{port}/proxy"

        def connect() -> ViewerClient | None:
            if viewer.poll() is not None:
                # A viewer that finds its port taken hands over to whoever holds it and exits.
                pytest.fail(f"the viewer exited ({viewer.returncode}): "
                            f"{log.read_text(errors='replace')[-3000:]}", pytrace=False)
            try:
                client = ViewerClient(url)
                client.get_state()
            except ConnectionError:
                return None
            return client

        client = wait_for(f"the viewer to answer on port {port} (log: {log})",
                          VIEWER_START_TIMEOUT_S, connect)
        assert client.get_state().viewer_version == rr.__version__
        yield client
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(viewer.pid, signal.SIGTERM)
        try:
            viewer.wait(timeout=EXIT_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            os.killpg(viewer.pid, signal.SIGKILL)
            viewer.wait()


def record_session(path: Path, prefixes: list[str]) -> int:
    """A short flight per vehicle prefix through Viewer, as the station logs it: keyframes of a
    wall 2 m ahead with a bump, renders, both health groups and a mesh. Its last capture time."""
    rng = np.random.default_rng(SEED)
    v, u = np.mgrid[0:HEIGHT, 0:WIDTH]
    bump_m = 0.3 * np.exp(-((u - WIDTH / 2) ** 2 + (v - HEIGHT / 2) ** 2) / 800.0)
    grid = np.linspace(-1.5, 1.5, 20)
    x, y = np.meshgrid(grid, grid)
    vertices = np.stack([x, y, 2.0 - 0.3 * np.exp(-(x ** 2 + y ** 2) / 0.2)], axis=-1)
    corners = np.arange(19 * 20).reshape(19, 20)[:, :19].ravel()
    triangles = np.concatenate([np.stack([corners, corners + 20, corners + 1], axis=1),
                                np.stack([corners + 1, corners + 20, corners + 21], axis=1)])
    viewer = Viewer(save_path=path)
    last_utime = T0_US
    for vehicle_id, prefix in enumerate(prefixes, start=1):
        view = viewer.vehicle(vehicle_id, prefix)
        for k in range(KEYFRAMES):
            last_utime = T0_US + k * KEYFRAME_PERIOD_US
            T_world_cam = np.eye(4)
            T_world_cam[:3, 3] = [0.05 * k, 0.0, 0.02 * k]
            depth_m = 2.0 - 0.02 * k - bump_m + rng.normal(0.0, 0.005, (HEIGHT, WIDTH))
            view.keyframe(last_utime, np.round(depth_m / DEPTH_SCALE_M).astype(np.uint16),
                          DEPTH_SCALE_M, INTRINSICS, T_world_cam, T_world_cam)
            view.render(last_utime, np.uint8(255 * (depth_m - depth_m.min()) / np.ptp(depth_m)),
                        depth_m.shape)
            view.health(last_utime, {
                "link/received": k + 1.0, "link/fused": k + 1.0, "link/not_refined": 0.0,
                "link/dropped": 0.0, "link/latency_ms": 20.0 + rng.normal(0.0, 2.0),
                "tracking/inlier_fraction": 0.9, "tracking/rmse_mm": 4.0 + rng.normal(0.0, 0.5)})
        view.mesh(last_utime, 0, vertices.reshape(-1, 3).astype(np.float32),
                  triangles.astype(np.int32), None)
    viewer.close()
    return last_utime


def show_the_end(client: ViewerClient, path: Path, last_utime: int) -> ViewerState:
    """Open PATH and stop the time cursor at its last capture time, where the mesh is."""
    client.open(str(path))
    end_ns = last_utime * 1000

    def loaded() -> ViewerState | None:
        state = client.get_state()
        recording = next((r for r in state.recordings if r.store_id == state.active_recording),
                         None)
        ends = [] if recording is None else [t.end for t in recording.timelines
                                             if t.name == TIMELINE]
        return state if not state.loading and state.views and ends == [end_ns] else None

    wait_for(f"{path.name} to load", LOAD_TIMEOUT_S, loaded)
    client.set_time(TIMELINE, timestamp=np.datetime64(last_utime, "us"), play_state="paused")
    return client.get_state()


def screenshot(client: ViewerClient, view: View | None = None) -> np.ndarray:
    """The whole viewer, or one VIEW, as painted, RGB. The call waits for a paint at most 15 s;
    a slower paint is asked for again."""
    def attempt() -> np.ndarray | None:
        try:
            png = client.take_screenshot(None if view is None else view.view_id)
        except (ConnectionError, TimeoutError) as error:
            if "NotFound" in str(error):  # a view not on screen: waiting will not help
                raise
            return None
        return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"))

    return wait_for("a screenshot", SCREENSHOT_TIMEOUT_S, attempt)


def drawn_fraction(picture: np.ndarray) -> float:
    """The share of pixels that differ from the picture's most common colour."""
    pixels = picture.reshape(-1, 3).astype(np.int16)
    colours, counts = np.unique(pixels, axis=0, return_counts=True)
    background = colours[counts.argmax()]
    return float((np.abs(pixels - background).max(axis=1) > BACKGROUND_TOLERANCE).mean())


@pytest.mark.parametrize("prefixes", [[""], ["vehicle_1/", "vehicle_2/"]],
                         ids=["one_vehicle", "two_vehicles"])
def test_viewer_shows_the_map_largest(display: str, prefixes: list[str], tmp_path: Path) -> None:
    recording = tmp_path / "session.rrd"
    last_utime = record_session(recording, prefixes)
    with running_viewer(display, tmp_path / "viewer.log") as client:
        state = show_the_end(client, recording, last_utime)
        views = {(view.view_class, view.origin): view for view in state.views}
        assert set(views) == {(kind, f"/{prefix}{origin}") for prefix in prefixes
                              for kind, origin in LAYOUT}
        # With several vehicles the first one's tab is on screen.
        shown = {kind_origin: view for kind_origin, view in views.items()
                 if kind_origin[1].startswith(f"/{prefixes[0]}")}
        map_key = ("3D", f"/{prefixes[0]}world")

        # The map painted with the recording in it is the readiness the pictures wait for.
        def map_painted() -> np.ndarray | None:
            picture = screenshot(client, shown[map_key])
            return picture if drawn_fraction(picture) >= MAP_DRAWN_FRACTION_MIN else None

        try:
            map_picture = wait_for(f"the map to be drawn (>= {MAP_DRAWN_FRACTION_MIN:.0%} of "
                                   "its pixels)", SCREENSHOT_TIMEOUT_S, map_painted)
        finally:
            whole = screenshot(client)
            Image.fromarray(whole).save(tmp_path / "viewer.png")
        pictures = {key: screenshot(client, view) for key, view in shown.items() if key != map_key}
        pictures[map_key] = map_picture
        # What the views reported at their last paint, the recording's end: while it loads a
        # view may briefly report data it has not received yet.
        reports = [(view.name, view.origin, view.reports) for view in client.get_state().views
                   if view.reports]
    assert not reports

    assert len(np.unique(whole.reshape(-1, 3), axis=0)) > 1, "one colour everywhere"
    assert whole.std() >= PICTURE_STD_MIN, (whole.std(), tmp_path / "viewer.png")
    areas = {key: picture.shape[0] * picture.shape[1] for key, picture in pictures.items()}
    largest_other = max(area for key, area in areas.items() if key != map_key)
    assert areas[map_key] >= MAP_AREA_RATIO_MIN * largest_other, (
        {f"{kind} {origin}": picture.shape[:2] for (kind, origin), picture in pictures.items()},
        tmp_path / "viewer.png")
