"""Geography: WGS84 local planes and UTM, metric scale and the georeference of a map from GPS, the
camera model (tilt to nadir), world-file and CRS sidecar texts."""
