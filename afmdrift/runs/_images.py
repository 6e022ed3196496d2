"""Image files of a run directory: written durably, read back with checks.

The run store keeps the registration reference (``reference-NNNNNN.npy``) and,
with ``archive_frames``, every frame (``frames/NNNNNN.npy``) next to its
database. A file is fsynced, with its directory entry, before the transaction
that names it commits; one read back that is missing, truncated or not an
image is reported and not used.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np
import numpy.typing as npt

__all__ = ["load_reference_image", "save_image"]

log = logging.getLogger(__name__)


def save_image(path: Path, image: npt.NDArray[np.floating]) -> None:
    """Write ``image`` as float32 ``.npy`` atomically and durably."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    try:
        with tmp.open("wb") as fh:
            np.save(fh, np.asarray(image, dtype=np.float32), allow_pickle=False)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        # a full disk: leave no partial file to take the space
        tmp.unlink(missing_ok=True)
        raise
    dir_fd = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(dir_fd)
    finally:
        os.close(dir_fd)


def load_reference_image(path: Path) -> npt.NDArray[np.float32] | None:
    """The reference image at ``path``, or ``None`` (reported) when it is missing
    or damaged: the next frame then becomes a new reference."""
    # Written (and fsynced) before the frame's transaction and deleted only
    # after a later one committed, so it is on disk unless something else
    # removed or damaged it.
    try:
        image = np.load(path, allow_pickle=False)
    except FileNotFoundError:
        log.warning("run store: reference image %s is missing; taking a new one", path)
        return None
    except (OSError, ValueError, EOFError) as err:
        log.warning("run store: reference image %s is damaged (%s); taking a new one", path, err)
        return None
    if image.ndim != 2 or not np.issubdtype(image.dtype, np.floating) or min(image.shape) < 2:
        log.warning(
            "run store: reference image %s is not a 2-D float image %s; taking a new one",
            path,
            image.shape,
        )
        return None
    return np.asarray(image, dtype=np.float32)
