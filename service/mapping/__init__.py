"""Mapping a flight: the worker thread that turns frames into the map, its events to sinks, loop
closure in the background, telemetry joined to frames, and the files a run writes."""
