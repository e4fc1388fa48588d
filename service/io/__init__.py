"""Files: atomic writers, trajectory and ground-truth formats (CSV, TUM), and the on-disk stores of map
tiles and keyframe images."""
