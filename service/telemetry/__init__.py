"""The telemetry model that drivers and mapping share: decoded, validated MAVLink samples in a
time-indexed buffer, and the video/telemetry time offset from yaw rates."""
