"""``mipslam view RUN_DIR``: serve a finished run folder in the browser (its refined map, ``refined/map.ply`` of
``mipslam refine``, where there is one, unless the SLAM map is asked for).

The page opens at the first frame; a slider picks any processed frame, whose image (read again
from the run's dataset when that is still where the run found it) is shown beside the map
rendered from the frame's estimated pose with the EAA footprint.
"""
from __future__ import annotations

import logging
import threading
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from mipslam.errors import MipslamError
from mipslam.types import Intrinsics
from mipslam.viewer.server import PANEL_IMAGE_WIDTH, ViewerOptions, ViewerServer
from mipslam.viewer.snapshot import RecordedRun, snapshot_from_run_dir, to_uint8_image

log = logging.getLogger(__name__)

# A sequence frame belongs to an estimated pose when their timestamps differ by less than this (seconds or
# frame numbers): the run wrote the sequence's own timestamps, so they agree to the file's printed precision.
TIMESTAMP_MATCH_TOLERANCE = 1e-4
# Cameras and their recordings are streams, not indexable folders: their frames are not read again here.
STREAM_KINDS = ("realsense", "realsense_bag")


def panel_intrinsics(intrinsics: Intrinsics, width: int = PANEL_IMAGE_WIDTH) -> Intrinsics:
    """The camera scaled down to at most ``width`` pixels wide (the size the page shows)."""
    return intrinsics.scaled(width / intrinsics.width) if intrinsics.width > width else intrinsics


@torch.no_grad()
def render_panel(gaussians, T_wc: np.ndarray, intrinsics: Intrinsics, render_config) -> np.ndarray:
    """The map rendered with the EAA footprint from ``T_wc`` [4, 4] at ``intrinsics`` -> [H, W, 3] uint8.

    gaussians: :class:`~mipslam.gaussians.ActivatedGaussians` (detached, CPU or the run's device)."""
    from mipslam.geometry import se3_inverse
    from mipslam.rendering import render_view

    T_cw = se3_inverse(torch.from_numpy(np.array(T_wc, dtype=np.float64)))  # a copy: run files are read-only arrays
    out = render_view(gaussians, T_cw, intrinsics, render_config, mode="eaa")
    return to_uint8_image(out.color.detach().cpu().numpy())


class RecordedViewer:
    """A run folder served by a :class:`ViewerServer`, with a frame slider."""

    def __init__(self, run_dir: str | Path, options: ViewerOptions = ViewerOptions(follow=False), *,
                 refined: bool = True):
        """``refined``: show the map of ``mipslam refine`` (``refined/map.ply``, its poses) where there is one."""
        self.run: RecordedRun = snapshot_from_run_dir(run_dir, refined=refined)
        self._sequence, self._sequence_index = self._open_sequence()
        self._gaussians = None
        self._render_lock = threading.Lock()
        self._pending: int | None = None
        frames = len(self.run.snapshot.est_T_wc)
        self.server = ViewerServer(options, title=f"mipslam · {self.run.run_dir.name}", frame_slider=frames,
                                   on_frame_selected=self.select_frame)
        first = replace(self.run.snapshot, current=0 if frames else -1)
        if frames and not options.map_only:
            first = replace(first, **self.images(0))
        self.server.show(first)

    @property
    def url(self) -> str:
        return self.server.url

    def describe_map(self) -> str:
        """Which map is shown (the SLAM map or the refined one), in words."""
        return self.run.describe_map()

    def close(self) -> None:
        self.server.close()

    def select_frame(self, position: int) -> None:
        """Show frame ``position`` of the estimate (slider callback; the newest request wins)."""
        self.server.move_current(position)
        self._pending = position
        if not self._render_lock.acquire(blocking=False):
            return  # the running render picks up the newest request when it finishes
        try:
            while self._pending is not None:
                wanted, self._pending = self._pending, None
                images = self.images(wanted)
                self.server.show_images(images["frame_image"], images["rendered_image"])
        finally:
            self._render_lock.release()

    # ------------------------------------------------------------------ frames
    def _open_sequence(self):
        """The run's dataset (to show the frames' images), or (None, {}) when it cannot be opened."""
        config = self.run.config
        if config is None or config.dataset.kind in STREAM_KINDS:
            return None, {}
        from mipslam.datasets import make_sequence

        try:
            sequence = make_sequence(config.dataset)
        except MipslamError as exc:
            log.info("frame images unavailable (%s); showing the map renders only", exc)
            return None, {}
        stamps = np.asarray(sequence.timestamps, dtype=np.float64)
        index = {}
        for position, stamp in enumerate(self.run.est_timestamps):
            k = int(np.searchsorted(stamps, stamp))
            for candidate in (k - 1, k):
                if 0 <= candidate < len(stamps) and abs(stamps[candidate] - stamp) < TIMESTAMP_MATCH_TOLERANCE:
                    index[position] = candidate
        return sequence, index

    def images(self, position: int) -> dict:
        """frame_image / rendered_image of estimated frame ``position`` (None where unavailable)."""
        frame_image = rendered = None
        intrinsics = self.run.snapshot.intrinsics
        if self._sequence is not None and position in self._sequence_index:
            try:
                frame = self._sequence[self._sequence_index[position]]
                frame_image = to_uint8_image(frame.color.numpy())
                intrinsics = frame.intrinsics
            except MipslamError as exc:
                log.info("frame %d: image unavailable (%s)", position, exc)
        if intrinsics is not None and self.run.config is not None:
            if self._gaussians is None:
                from mipslam.io.ply import read_map_ply

                self._gaussians = read_map_ply(self.run.map_file or self.run.run_dir / "map.ply").activated().detached()
            rendered = render_panel(self._gaussians, self.run.snapshot.est_T_wc[position], panel_intrinsics(intrinsics),
                                    self.run.config.render)
        return {"frame_image": frame_image, "rendered_image": rendered}
