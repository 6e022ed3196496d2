"""Readers for image files: .npy, .tif, NanoScope, Gwyddion, HS-AFM .asd, NetCDF.

:func:`load_image` reads one height image (``FILE`` or ``FILE:i`` for frame
``i`` of a movie or stack) and :func:`load_stack` every frame of a file, as
:class:`AfmImage` records with heights in nm and the pixel size (x, y) in nm.
Format readers (AFMReader, tifffile, scipy) are imported only when used.
"""

from afmdrift.io._image import AfmImage, ImageFileError, length_unit_to_nm
from afmdrift.io._load import SUFFIXES, PixelSize, load_image, load_stack, parse_spec
from afmdrift.io._nanoscope import NanoscopeHeader, parse_nanoscope_header

__all__ = [
    "SUFFIXES",
    "AfmImage",
    "ImageFileError",
    "NanoscopeHeader",
    "PixelSize",
    "length_unit_to_nm",
    "load_image",
    "load_stack",
    "parse_nanoscope_header",
    "parse_spec",
]
