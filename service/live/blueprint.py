"""The default layout of the operator view in rerun (declared in code, as rerun's examples do)."""

from __future__ import annotations

import rerun.blueprint as rrb


def default_blueprint() -> rrb.Blueprint:
    """Map on the left (a second tab: the GPS track and footprint on web tiles); the live camera,
    health plots and events stacked on the right.

    The entity roots match :mod:`photomap.live.viewer`: ``/map`` (tiles, trajectory, footprint),
    ``/geo`` (GPS position, footprint, keyframes, track), ``/camera``, ``/health`` and ``/telemetry`` (time series) and ``/events`` (text log).
    """
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Tabs(rrb.Spatial2DView(origin="/map", name="Map"),
                     rrb.MapView(origin="/geo", name="Geo (GPS)")),
            rrb.Vertical(
                rrb.Spatial2DView(origin="/camera", name="Camera"),
                rrb.Tabs(rrb.TimeSeriesView(origin="/health", name="Health"),
                         rrb.TimeSeriesView(origin="/telemetry", name="Telemetry")),
                rrb.TextLogView(origin="/events", name="Events"),
                row_shares=[3, 3, 2],
            ),
            column_shares=[3, 2],
        ),
    )
