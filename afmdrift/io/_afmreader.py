"""Lazy, quiet access to AFMReader.

AFMReader logs every step through loguru and each of its modules calls
``logger.enable("AFMReader...")`` when it is imported, so a single
``logger.disable`` before the import is undone. We import the module first and
disable its logging afterwards, every time, which keeps afmdrift's output clean.
"""

from __future__ import annotations

import importlib
from types import ModuleType

__all__ = ["afmreader_module"]


def afmreader_module(name: str) -> ModuleType:
    """Import ``AFMReader.<name>`` (``spm``, ``asd``, ...) with its logging disabled."""
    module = importlib.import_module(f"AFMReader.{name}")
    from loguru import logger

    logger.disable("AFMReader")
    return module
