"""Readers for image files: .npy, .tif, NanoScope, Gwyddion, HS-AFM .asd, NetCDF."""
