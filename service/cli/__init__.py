"""The `photomap` command: one thin module per command, and the wiring they share (frame source,
telemetry, pipeline with its sinks, signals)."""
