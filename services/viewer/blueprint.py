"""The layout a Rerun viewer opens the recording with.

Left: a 3D view of the world frame (cameras as frusta with their images, poses, truth,
trajectories, points) above tabs of node health (stream rates, processing p50/p99, dropped
frames, decode errors, stage times, error reports). Right: one 2D view per camera (its image with the
detection overlays), in order of appearance; a marker node's AR overlay of camera ``cam0``
is the camera ``cam0/overlay`` here, with a view of its own. The time panel starts on the
``stamp`` timeline. The blueprint is sent again whenever a camera appears.
"""

from __future__ import annotations

from collections.abc import Sequence

import rerun.blueprint as rrb

from services.viewer import layout

HEALTH = ((layout.RATE_HZ, "rates (Hz)"), (layout.PROCESSING_MS, "processing (ms)"),
          (layout.LATENCY_MS, "latency (ms)"), (layout.DROPPED, "dropped"), (layout.DECODE_ERRORS, "decode errors"),
          (layout.STAGE_MS, "stages (ms)"))


def blueprint(cameras: Sequence[str]) -> rrb.Blueprint:
    """The viewer's layout for the cameras seen so far."""
    health = rrb.Tabs(*(rrb.TimeSeriesView(origin=layout.stats(metric), name=name) for metric, name in HEALTH),
                      rrb.TextLogView(origin=layout.LOGS, name="errors"))
    main: rrb.Container = rrb.Vertical(rrb.Spatial3DView(origin=layout.WORLD, name="rig"), health, row_shares=[3, 2])
    if cameras:
        images = rrb.Grid(*(rrb.Spatial2DView(origin=layout.image(camera), name=camera) for camera in cameras))
        main = rrb.Horizontal(main, images)
    return rrb.Blueprint(main, rrb.TimePanel(timeline=layout.STAMP))
