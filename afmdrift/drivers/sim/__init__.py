"""The simulated AFM: physics, sample, raster scanner, and protocol server."""
