"""The live viewer: an observer of the frame loop that shows the run in the browser while it runs.

The viewer is the run's :class:`~mipslam.observer.Observer` (``run_slam(..., observer=viewer)``): its
:meth:`LiveViewer.on_frame` runs after every frame, outside the stage timings.
The call returns at once unless a capture is due; a capture copies what the page needs (the map's
raw parameters, the poses, the loop edges, the current frame: detached CPU tensors, a few
milliseconds) and hands it to a queue of size one (a newer capture replaces one not yet drawn).
A viewer thread turns captures into snapshots (activation, covariances, the EAA render of the map
from the frame's estimated pose) and sends them to the page.

The viewer never changes the run: it reads the state and copies it, it draws no random numbers
and sets no torch options, so the trajectory is bit-identical with and without it. It never
blocks the run either: captures are throttled so that the viewer thread works at most
``max_busy_fraction`` of the wall time (and not more often than every ``min_interval_s``), and an
error inside the viewer turns the viewer off with a warning, never the run.
"""
from __future__ import annotations

import logging
import queue
import threading
import time
from dataclasses import dataclass, replace

import numpy as np
import torch

from mipslam.observer import Observer
from mipslam.types import Intrinsics
from mipslam.viewer.server import ViewerOptions, ViewerServer
from mipslam.viewer.snapshot import Headline, SceneSnapshot, Splats, aligned_ate_rmse, to_uint8_image

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class LiveOptions:
    """How often the live viewer looks at the run."""

    min_interval_s: float = 0.5  # at most two updates per second
    max_busy_fraction: float = 0.05  # the viewer thread works at most this share of the wall time


@dataclass(frozen=True)
class Capture:
    """What the loop thread copies for one update (CPU tensors, owned by the capture).

    raw map parameters as in :class:`~mipslam.gaussians.GaussianMap` ([N, 3], [N, 4], [N, 3], [N], [N, 3]);
    est_T_wc [F, 4, 4] float64; keyframe_T_wc [K, 4, 4] float64; loop_edges [E, 2] int64 keyframe ids;
    color [H, W, 3] float32 of the current frame and its exposure [2] (log gain, bias).
    """

    means: torch.Tensor
    quats_wxyz: torch.Tensor
    log_scales: torch.Tensor
    opacity_logits: torch.Tensor
    colors_raw: torch.Tensor
    est_T_wc: torch.Tensor
    keyframe_T_wc: torch.Tensor
    loop_edges: torch.Tensor
    color: torch.Tensor
    exposure: torch.Tensor
    intrinsics: Intrinsics
    headline: Headline


def _copy(tensor: torch.Tensor) -> torch.Tensor:
    return tensor.detach().to("cpu", copy=True)


class LiveViewer(Observer):
    """Serve the page and keep it up to date with the run; pass it to ``run_slam(observer=...)``.

    render_config: the run's :class:`~mipslam.config.RenderConfig` (the page's render uses its
    constants with the EAA footprint); diagnostics: as :class:`~mipslam.observer.Observer`'s
    (the run's ``run.diagnostics``). As an observer it also records the run's stage timings.
    """

    def __init__(self, render_config, options: ViewerOptions = ViewerOptions(), live: LiveOptions = LiveOptions(),
                 *, diagnostics: bool = False):
        super().__init__(diagnostics=diagnostics)
        self.render_config = render_config
        self.live = live
        self.server = ViewerServer(options, title="mipslam · live")
        self._queue: queue.Queue[Capture | None] = queue.Queue(maxsize=1)
        self._next_capture_at = 0.0  # perf_counter seconds; the first frame is captured at once
        self._first_call: float | None = None
        self._frames_seen = 0
        self._gt: tuple[np.ndarray, np.ndarray] | None = None  # (gt positions [N, 3], valid [N]) of the sequence
        self._failed = False
        self._finished = False
        self.captures = 0  # captures taken (frames the page was updated for, at most)
        self.updates = 0  # snapshots drawn
        self.busy_s = 0.0  # seconds the viewer thread worked
        self.capture_s = 0.0  # seconds the loop thread spent on captures
        self._thread = threading.Thread(target=self._work, name="mipslam-viewer", daemon=True)
        self._thread.start()

    @property
    def url(self) -> str:
        return self.server.url

    # ------------------------------------------------------------------ loop thread
    def on_frame(self, record, state) -> None:
        """After frame ``record``: take a capture when one is due and the previous one was drawn."""
        if self._failed:
            return
        now = time.perf_counter()
        if self._first_call is None:
            self._first_call = now
        self._frames_seen += 1
        if now < self._next_capture_at or not self._queue.empty():
            return
        try:
            capture = self._capture(self.frames, state, record, now)
        except Exception as exc:  # the viewer must never stop the run
            self._fail(exc)
            return
        self.captures += 1
        self.capture_s += time.perf_counter() - now
        self._next_capture_at = float("inf")  # the viewer thread sets the next time once it has drawn this one
        self._offer(capture)

    def _capture(self, frames, state, record, now: float) -> Capture:
        gmap = state.gaussian_map
        sequence = frames.sequence
        if self._gt is None:
            gt = sequence.gt_T_wc
            self._gt = ((gt[:, :3, 3].numpy().copy(), np.asarray(sequence.gt_valid, dtype=bool).copy())
                        if gt is not None else (np.zeros((0, 3)), np.zeros(0, dtype=bool)))
        graph = state.loop.graph
        frame = frames[record.index]
        elapsed = now - (self._first_call or now)
        fps = (self._frames_seen - 1) / elapsed if elapsed > 0 and self._frames_seen > 1 else None
        total = len(sequence) if sequence.random_access else 0  # a stream's length is unknown
        headline = Headline(frame=state.next_frame, total_frames=total, frames_per_second=fps,
                            gaussians=len(gmap), keyframes=len(state.keyframe_frames))
        return Capture(
            means=_copy(gmap.means), quats_wxyz=_copy(gmap.quats_wxyz), log_scales=_copy(gmap.log_scales),
            opacity_logits=_copy(gmap.opacity_logits), colors_raw=_copy(gmap.colors_raw),
            est_T_wc=state.poses(), keyframe_T_wc=state.keyframe_poses(),
            loop_edges=_copy(graph.edge_nodes[graph.edge_is_loop]), color=_copy(frame.color),
            exposure=_copy(record.exposure), intrinsics=frame.intrinsics, headline=headline,
        )

    def _offer(self, capture: Capture | None) -> None:
        """Put ``capture`` in the size-one queue, dropping one the viewer thread has not taken yet."""
        while True:
            try:
                self._queue.put_nowait(capture)
                return
            except queue.Full:
                try:
                    self._queue.get_nowait()
                except queue.Empty:
                    pass

    def _fail(self, exc: BaseException) -> None:
        self._failed = True
        log.warning("viewer: turned off after an error (%s: %s); the run goes on", type(exc).__name__, exc)

    # ------------------------------------------------------------------ viewer thread
    def _work(self) -> None:
        while True:
            capture = self._queue.get()
            if capture is None:
                return
            started = time.perf_counter()
            try:
                self.server.show(self.snapshot(capture))
                self.updates += 1
            except Exception as exc:
                self._fail(exc)
                return
            finished = time.perf_counter()
            cost = finished - started
            self.busy_s += cost
            self._next_capture_at = finished + max(self.live.min_interval_s, cost / self.live.max_busy_fraction)

    @torch.no_grad()
    def snapshot(self, capture: Capture) -> SceneSnapshot:
        """The page's content for ``capture`` (runs on the viewer thread)."""
        from mipslam.gaussians import ActivatedGaussians
        from mipslam.losses.photometric import apply_affine_exposure
        from mipslam.viewer.recorded import panel_intrinsics
        from mipslam.rendering import render_view
        from mipslam.geometry import se3_inverse

        quats = capture.quats_wxyz / capture.quats_wxyz.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        gaussians = ActivatedGaussians(means=capture.means, quats=quats, scales=capture.log_scales.exp(),
                                       opacities=torch.sigmoid(capture.opacity_logits),
                                       colors=torch.sigmoid(capture.colors_raw))
        splats = Splats.from_activated(gaussians.means.numpy(), quats.numpy(), gaussians.scales.numpy(),
                                       gaussians.colors.numpy(), gaussians.opacities.numpy())
        est_T_wc = capture.est_T_wc.numpy()
        rendered = None
        if len(gaussians) and len(est_T_wc):
            T_cw = se3_inverse(capture.est_T_wc[-1])
            out = render_view(gaussians, T_cw, panel_intrinsics(capture.intrinsics), self.render_config, mode="eaa")
            log_gain, bias = capture.exposure.to(out.color)
            color = apply_affine_exposure(out.color, log_gain, bias)
            rendered = to_uint8_image(color.numpy())
        gt_positions, ate = None, None
        if self._gt is not None and self._gt[1].any():
            positions, valid = self._gt
            count = min(len(est_T_wc), len(valid))
            mask = valid[:count]
            gt_positions = positions[:count][mask]
            ate = aligned_ate_rmse(est_T_wc[:count, :3, 3][mask], gt_positions)
        headline = replace(capture.headline, ate_rmse_m=ate)
        return SceneSnapshot(splats=splats, est_T_wc=est_T_wc, keyframe_T_wc=capture.keyframe_T_wc.numpy(),
                             headline=headline, gt_positions=gt_positions, loop_edges=capture.loop_edges.numpy(),
                             current=len(est_T_wc) - 1, frame_image=to_uint8_image(capture.color.numpy()),
                             rendered_image=rendered, intrinsics=capture.intrinsics)

    # ------------------------------------------------------------------ end
    def finish(self, run_dir=None, timeout_s: float = 30.0) -> None:
        """Stop taking captures, let the viewer thread finish, then show the finished run folder (its final
        map after refinement, and its metrics) when ``run_dir`` is given."""
        if self._finished:
            return
        self._finished = True
        self._failed = True  # no more captures
        self._offer(None)
        self._thread.join(timeout=timeout_s)
        log.info("viewer: %d updates; the loop spent %.3f s on %d captures, the viewer thread worked %.2f s",
                 self.updates, self.capture_s, self.captures, self.busy_s)
        if run_dir is None:
            return
        from mipslam.errors import MipslamError
        from mipslam.viewer.snapshot import snapshot_from_run_dir

        try:
            self.server.show(snapshot_from_run_dir(run_dir).snapshot)
        except MipslamError as exc:
            log.warning("viewer: cannot show the finished run (%s)", exc)

    def close(self) -> None:
        self.finish()
        self.server.close()
