"""The browser viewer: a viser server that draws :class:`~mipslam.viewer.snapshot.SceneSnapshot` s.

viser (``pip install 'mipslam[viewer]'``) serves a web page that draws Gaussian splats with WebGL
in the browser, so the machine that runs mipslam needs no GPU. The page shows the map as splats,
the estimated trajectory (orange) and the ground truth where known (green), keyframe camera
frusta (blue), loop-closure edges between keyframes (magenta), the current camera (red, with its
image), the current frame beside the map rendered from its estimated pose, and the headline
numbers. It listens on 127.0.0.1 unless another address is asked for.

Coordinates are mipslam's world frame (metres); the scene's up direction is the first camera's
-y axis (OpenCV cameras look along +z with y down), which is "up" for a camera held upright.
"""
from __future__ import annotations

import contextlib
import io
import logging
import math
import threading
from dataclasses import dataclass, replace
from typing import Callable

import numpy as np

from mipslam.optional import import_optional
from mipslam.errors import MipslamError
from mipslam.types import Intrinsics
from mipslam.viewer.snapshot import SceneSnapshot, matrix_to_quaternion_wxyz

log = logging.getLogger(__name__)

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 8080

# Overlay colours (RGB 0-255), chosen apart from each other and from typical scene colours.
ESTIMATE_RGB = (255, 140, 0)
GROUND_TRUTH_RGB = (30, 170, 60)
KEYFRAME_RGB = (40, 90, 230)
LOOP_RGB = (220, 30, 170)
CURRENT_RGB = (230, 40, 40)
LINE_WIDTH_PX = 2.0
# Frustum depth as a fraction of the trajectory's extent (bounded below by MIN_FRUSTUM_M).
FRUSTUM_FRACTION, MIN_FRUSTUM_M = 0.06, 0.03
# Images sent to the page are at most this wide (pixels); the browser scales them.
PANEL_IMAGE_WIDTH = 320


def import_viser():
    """The viser module, or MipslamError saying how to install it."""
    return import_optional("viser", needed_by="the web viewer",
                           install="install it with pip install 'mipslam[viewer]' (or pip install viser)")


@dataclass(frozen=True)
class ViewerOptions:
    """How the page is served and what it shows first."""

    host: str = DEFAULT_HOST  # 127.0.0.1: only this machine; 0.0.0.0 exposes the viewer to the network
    port: int = DEFAULT_PORT  # the next free port is taken when this one is busy (0 = any free port)
    follow: bool = True  # move the browser's camera with the current frame
    map_only: bool = False  # draw the Gaussians alone (no trajectories, cameras or image panels)


class ViewerServer:
    """A viser server with mipslam's scene layers; :meth:`show` replaces them with a new snapshot.

    Thread-safe: :meth:`show` may be called from any one thread while the page's controls call back
    from viser's threads. ``on_frame_selected`` (recorded runs) is called with a frame position when
    the user moves the frame slider.
    """

    def __init__(self, options: ViewerOptions = ViewerOptions(), *, title: str = "mipslam",
                 frame_slider: int = 0, on_frame_selected: Callable[[int], None] | None = None):
        viser = import_viser()
        self.options = options
        self._lock = threading.RLock()
        self._last: SceneSnapshot | None = None
        self._up_set = False
        with _quiet():  # viser prints a banner; the CLI says where the page is
            try:
                self._server = viser.ViserServer(host=options.host, port=options.port, verbose=False)
            except OSError as exc:
                raise MipslamError(f"cannot serve the viewer on {options.host}:{options.port} ({exc}); "
                                   "choose another --viewer-host / --viewer-port") from None
        server = self._server
        server.gui.configure_theme(show_logo=False, show_share_button=False, control_width="medium")
        server.gui.set_panel_label(title)
        self._headline = server.gui.add_markdown("waiting for the first frame ...")
        self._slider = None
        if frame_slider > 1 and on_frame_selected is not None:
            self._slider = server.gui.add_slider("frame", min=0, max=frame_slider - 1, step=1, initial_value=0)
            self._slider.on_update(lambda _: on_frame_selected(int(self._slider.value)))
        self._follow = server.gui.add_checkbox("follow camera", initial_value=options.follow)
        self._layer_boxes = {}
        with server.gui.add_folder("layers", expand_by_default=False):
            for name, label in (("map", "Gaussians"), ("trajectory", "trajectories"), ("keyframes", "keyframes"),
                                ("loops", "loop closures"), ("camera", "current camera")):
                box = server.gui.add_checkbox(label, initial_value=not options.map_only or name == "map")
                box.on_update(lambda _, name=name: self._set_visible(name))
                self._layer_boxes[name] = box
        blank = np.full((36, 48, 3), 255, np.uint8)
        with server.gui.add_folder("current frame", expand_by_default=not options.map_only):
            self._frame_image = server.gui.add_image(blank, label="frame", format="jpeg")
            self._render_image = server.gui.add_image(blank, label="map at the estimated pose (EAA)", format="jpeg")
        self._handles: dict[str, list] = {}

    # ------------------------------------------------------------------ public
    @property
    def url(self) -> str:
        host = self._server.get_host()
        shown = "localhost" if host in ("0.0.0.0", "::") else host
        return f"http://{shown}:{self._server.get_port()}"

    @property
    def port(self) -> int:
        return int(self._server.get_port())

    @property
    def clients(self) -> int:
        """Pages connected now."""
        return len(self._server.get_clients())

    @property
    def shown(self) -> SceneSnapshot | None:
        """What the page shows now (the last snapshot, with the current frame and images it was given since)."""
        with self._lock:
            return self._last

    def show(self, snapshot: SceneSnapshot) -> None:
        """Replace every layer with ``snapshot``'s content (and move the browsers' cameras when following)."""
        with self._lock:
            self._last = snapshot
            scene = self._server.scene
            extent = _extent(snapshot)
            frustum_m = max(MIN_FRUSTUM_M, FRUSTUM_FRACTION * extent)
            if not self._up_set and len(snapshot.est_T_wc):
                up = -snapshot.est_T_wc[0][:3, 1]
                scene.set_up_direction(tuple(float(v) for v in up))
                self._up_set = True
            self._headline.content = snapshot.headline.markdown()
            if len(snapshot.splats):
                s = snapshot.splats
                self._put("map", scene.add_gaussian_splats("/map", centers=s.means, covariances=s.covariances,
                                                           rgbs=s.colors, opacities=s.opacities[:, None]))
            self._draw_trajectories(snapshot)
            self._draw_keyframes(snapshot, frustum_m)
            self._draw_loops(snapshot)
            self._draw_current(snapshot, frustum_m)
            self._show_images(snapshot.frame_image, snapshot.rendered_image)
            self._place_cameras(snapshot, extent)

    def show_images(self, frame_image: np.ndarray | None, rendered_image: np.ndarray | None) -> None:
        with self._lock:
            if self._last is not None:
                self._last = replace(self._last, frame_image=frame_image, rendered_image=rendered_image)
            self._show_images(frame_image, rendered_image)

    def move_current(self, position: int) -> None:
        """Show frame ``position`` of the last snapshot's trajectory as the current camera (recorded runs)."""
        with self._lock:
            if self._last is None or not 0 <= position < len(self._last.est_T_wc):
                return
            self._last = replace(self._last, current=position)
            extent = _extent(self._last)
            self._draw_current(self._last, max(MIN_FRUSTUM_M, FRUSTUM_FRACTION * extent))
            self._place_cameras(self._last, extent)

    def close(self) -> None:
        with _quiet():
            self._server.stop()

    # ------------------------------------------------------------------ layers
    def _put(self, layer: str, handle) -> None:
        """Record a scene node of ``layer`` (replacing a node of the same name replaces it in the page)."""
        handles = self._handles.setdefault(layer, [])
        if all(h.name != handle.name for h in handles):
            handles.append(handle)
        else:
            handles[:] = [handle if h.name == handle.name else h for h in handles]
        handle.visible = bool(self._layer_boxes[layer].value)

    def _set_visible(self, layer: str) -> None:
        with self._lock:
            for handle in self._handles.get(layer, []):
                handle.visible = bool(self._layer_boxes[layer].value)

    def _draw_trajectories(self, snapshot: SceneSnapshot) -> None:
        scene = self._server.scene
        est = snapshot.est_T_wc[:, :3, 3]
        if len(est) >= 2:
            self._put("trajectory", scene.add_line_segments(
                "/trajectory/estimate", _polyline(est), ESTIMATE_RGB, thickness=LINE_WIDTH_PX,
                thickness_units="screen"))
        gt = snapshot.gt_positions
        if gt is not None and len(gt) >= 2:
            self._put("trajectory", scene.add_line_segments(
                "/trajectory/ground_truth", _polyline(gt), GROUND_TRUTH_RGB, thickness=LINE_WIDTH_PX,
                thickness_units="screen"))

    def _draw_keyframes(self, snapshot: SceneSnapshot, depth_m: float) -> None:
        if not len(snapshot.keyframe_T_wc):
            return
        segments = frustum_segments(snapshot.keyframe_T_wc, snapshot.intrinsics, depth_m)
        self._put("keyframes", self._server.scene.add_line_segments(
            "/keyframes", segments, KEYFRAME_RGB, thickness=1.5, thickness_units="screen"))

    def _draw_loops(self, snapshot: SceneSnapshot) -> None:
        edges = snapshot.loop_edges
        K = len(snapshot.keyframe_T_wc)
        edges = edges[(edges >= 0).all(1) & (edges < K).all(1)] if len(edges) else edges
        if not len(edges):
            return
        centres = snapshot.keyframe_T_wc[:, :3, 3]
        segments = np.stack([centres[edges[:, 0]], centres[edges[:, 1]]], axis=1)  # [E, 2, 3]
        self._put("loops", self._server.scene.add_line_segments(
            "/loops", segments, LOOP_RGB, thickness=LINE_WIDTH_PX + 1, thickness_units="screen"))

    def _draw_current(self, snapshot: SceneSnapshot, depth_m: float) -> None:
        if not 0 <= snapshot.current < len(snapshot.est_T_wc):
            return
        T_wc = snapshot.est_T_wc[snapshot.current]
        fov, aspect = _fov_aspect(snapshot.intrinsics)
        image = _thumbnail(snapshot.frame_image, 160) if snapshot.frame_image is not None else None
        self._put("camera", self._server.scene.add_camera_frustum(
            "/camera", fov=fov, aspect=aspect, scale=depth_m * 1.5, color=CURRENT_RGB, image=image,
            format="jpeg", thickness=2.5, thickness_units="screen",
            wxyz=matrix_to_quaternion_wxyz(T_wc[:3, :3]), position=T_wc[:3, 3]))

    def _show_images(self, frame_image, rendered_image) -> None:
        if frame_image is not None:
            self._frame_image.image = _thumbnail(frame_image, PANEL_IMAGE_WIDTH)
        if rendered_image is not None:
            self._render_image.image = _thumbnail(rendered_image, PANEL_IMAGE_WIDTH)

    def _place_cameras(self, snapshot: SceneSnapshot, extent: float) -> None:
        """Put the browsers' view behind and above the current camera: the start view of new pages,
        and every open page's view while "follow camera" is on."""
        if not 0 <= snapshot.current < len(snapshot.est_T_wc):
            return
        eye, look_at, up = follow_view(snapshot.est_T_wc[snapshot.current], extent)
        fov, _ = _fov_aspect(snapshot.intrinsics)
        initial = self._server.initial_camera
        initial.position, initial.look_at, initial.up, initial.fov = eye, look_at, up, fov
        if not self._follow.value:
            return
        for client in self._server.get_clients().values():
            with client.atomic():
                client.camera.up_direction = up
                client.camera.position = eye
                client.camera.look_at = look_at


# ----------------------------------------------------------------------------- geometry helpers

def follow_view(T_wc: np.ndarray, extent: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(eye, look_at, up) of a chase view of camera ``T_wc`` [4, 4]: behind it and a little above,
    looking where it looks; distances scale with the scene's extent (metres)."""
    R, c = T_wc[:3, :3], T_wc[:3, 3]
    forward, up = R[:, 2], -R[:, 1]
    back = min(max(0.3 * extent, 0.3), 3.0)
    eye = c - back * forward + 0.4 * back * up
    return eye, c + back * forward, up


def frustum_segments(T_wc: np.ndarray, intrinsics: Intrinsics | None, depth_m: float) -> np.ndarray:
    """Wireframe of camera frusta: 4 edges from the centre and 4 around the image at ``depth_m``.

    T_wc [K, 4, 4] -> segments [8K, 2, 3] (world metres)."""
    if intrinsics is None:
        corners = np.array([[-0.5, -0.375], [0.5, -0.375], [0.5, 0.375], [-0.5, 0.375]])  # a 4:3 view, 53 deg wide
    else:
        i = intrinsics
        u = np.array([-0.5, i.width - 0.5, i.width - 0.5, -0.5])
        v = np.array([-0.5, -0.5, i.height - 0.5, i.height - 0.5])
        corners = np.stack([(u - i.cx) / i.fx, (v - i.cy) / i.fy], axis=1)
    local = np.concatenate([corners, np.ones((4, 1))], axis=1) * depth_m  # [4, 3] camera frame
    world = np.einsum("kij,cj->kci", T_wc[:, :3, :3], local) + T_wc[:, None, :3, 3]  # [K, 4, 3]
    centre = np.repeat(T_wc[:, None, :3, 3], 4, axis=1)  # [K, 4, 3]
    spokes = np.stack([centre, world], axis=2)  # [K, 4, 2, 3]
    rim = np.stack([world, np.roll(world, -1, axis=1)], axis=2)  # [K, 4, 2, 3]
    return np.concatenate([spokes, rim], axis=1).reshape(-1, 2, 3).astype(np.float32)


def _polyline(points: np.ndarray) -> np.ndarray:
    """Consecutive points [N, 3] as segments [N-1, 2, 3]."""
    points = np.asarray(points, dtype=np.float32)
    return np.stack([points[:-1], points[1:]], axis=1)


def _extent(snapshot: SceneSnapshot) -> float:
    """The trajectory's extent (metres): the largest side of its bounding box, or of the map's when the
    camera has barely moved."""
    positions = snapshot.est_T_wc[:, :3, 3]
    extent = float(np.ptp(positions, axis=0).max()) if len(positions) >= 2 else 0.0
    if extent < 0.5 and len(snapshot.splats):
        means = snapshot.splats.means
        lo, hi = np.percentile(means, [5, 95], axis=0)
        extent = max(extent, 0.5 * float((hi - lo).max()))
    return extent if math.isfinite(extent) else 1.0


def _fov_aspect(intrinsics: Intrinsics | None) -> tuple[float, float]:
    """Vertical field of view (radians) and width/height of the camera (a 4:3, 60-degree default)."""
    if intrinsics is None:
        return math.radians(60.0), 4.0 / 3.0
    return 2.0 * math.atan(intrinsics.height / (2.0 * intrinsics.fy)), intrinsics.width / intrinsics.height


def _thumbnail(image: np.ndarray, width: int) -> np.ndarray:
    """[H, W, 3] uint8 reduced by an integer factor to at most ``width`` pixels wide (area average)."""
    factor = int(math.ceil(image.shape[1] / width))
    if factor <= 1:
        return np.ascontiguousarray(image)
    H, W = (image.shape[0] // factor) * factor, (image.shape[1] // factor) * factor
    blocks = image[:H, :W].reshape(H // factor, factor, W // factor, factor, 3).astype(np.float32)
    return (blocks.mean(axis=(1, 3)) + 0.5).astype(np.uint8)


@contextlib.contextmanager
def _quiet():
    """Swallow what viser prints to stdout (its banner and 'server stopped')."""
    with contextlib.redirect_stdout(io.StringIO()):
        yield
