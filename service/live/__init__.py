"""The live operator view: the mapping run streamed to rerun (mosaic, track, camera, health) and
its blueprint."""
