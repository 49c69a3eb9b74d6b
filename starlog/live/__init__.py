"""``starlog live``: the pipeline on a camera while it records (placeholder, filled below)."""

from __future__ import annotations

from starlog.live.pace import simulate_realtime, write_at_camera_rate

__all__ = ["simulate_realtime", "write_at_camera_rate"]
