"""The core: iFMI registration, tracking (poses, keyframes, segments), the tiled map and the pose
graph. Pure: arrays in, arrays out; no I/O, threads, logging or globals. Conventions:
:mod:`photomap.geometry`."""
