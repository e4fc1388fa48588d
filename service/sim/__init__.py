"""The simulator, our ground truth: a pinhole camera flown over a terrain image along a known
trajectory, writing the video or stills, a MAVLink log and the exact frame-to-terrain matrices."""
