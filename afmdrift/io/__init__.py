"""Readers for image files: .npy, .tif, NanoScope, Gwyddion, HS-AFM .asd, NetCDF, Nanonis
.sxm, Asylum .ibw, JPK .jpk/.h5-jpk, WSxM .stp.

:func:`load_image` reads one height image (``FILE`` or ``FILE:i`` for frame
``i`` of a movie or stack) and :func:`load_stack` every frame of a file, as
:class:`AfmImage` records with heights in nm and the pixel size (x, y) in nm.
Format readers (AFMReader, igor2, tifffile, h5py, scipy) are imported only when used.
:func:`pick_channel` finds a file's height channel for the default ``Height``
(``HeightRetrace``, ``ZSensor``, ``Z``, ``Topography``, ...).
:func:`write_tif` and :func:`write_sxm` save simulator frames as instrument
software would (for the folder instrument's tests and benchmark).
"""

from afmdrift.io._channels import DEFAULT_CHANNEL, pick_channel
from afmdrift.io._image import AfmImage, ImageFileError, MissingPixelSizeError, length_unit_to_nm
from afmdrift.io._load import (
    SINGLE_IMAGE_SUFFIXES,
    SUFFIXES,
    PixelSize,
    calibrated,
    holds_one_image,
    is_image_file,
    load_image,
    load_stack,
    parse_spec,
)
from afmdrift.io._nanoscope import NanoscopeHeader, parse_nanoscope_header
from afmdrift.io._sxm import write_sxm
from afmdrift.io._write import write_tif

__all__ = [
    "DEFAULT_CHANNEL",
    "SINGLE_IMAGE_SUFFIXES",
    "SUFFIXES",
    "AfmImage",
    "ImageFileError",
    "MissingPixelSizeError",
    "NanoscopeHeader",
    "PixelSize",
    "calibrated",
    "holds_one_image",
    "is_image_file",
    "length_unit_to_nm",
    "load_image",
    "load_stack",
    "parse_nanoscope_header",
    "parse_spec",
    "pick_channel",
    "write_sxm",
    "write_tif",
]
