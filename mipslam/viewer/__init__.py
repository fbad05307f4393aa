"""Optional web viewer (viser): the map as splats, trajectories, keyframes and loop closures in a browser.

``mipslam view RUN_DIR`` serves a finished run (:class:`~mipslam.viewer.recorded.RecordedViewer`);
``mipslam run ... --viewer`` shows a run live (:class:`~mipslam.viewer.live.LiveViewer`, fed by
snapshots from the frame loop on another thread, never blocking it). Install with
``pip install 'mipslam[viewer]'``; viser is imported only when a viewer starts.
"""
from mipslam.viewer.snapshot import Headline, SceneSnapshot, Splats, snapshot_from_run_dir

__all__ = ["Headline", "SceneSnapshot", "Splats", "snapshot_from_run_dir"]
