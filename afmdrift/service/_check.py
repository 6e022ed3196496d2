"""The checks ``afmdrift run`` makes before it starts, shared with ``config check``.

Validating a file (:func:`afmdrift.config.load_config`) checks keys, types and
ranges. Running also needs what only the other layers know: the predictor and
its effect terms and plugins, the CURVE key files of exposed endpoints, and an
instrument URL the drivers understand. ``afmdrift config check`` runs exactly
these, so a configuration it passes is one ``run`` accepts.

Configuration files are trusted input: an effect plugin named in
``[model.physics] plugins`` is imported, which runs its code.
"""

from __future__ import annotations

from afmdrift.config import AfmdriftConfig
from afmdrift.drivers import FolderInstrument, Instrument
from afmdrift.errors import ConfigError
from afmdrift.model import Predictor, make_predictor
from afmdrift.service._runner import open_instrument
from afmdrift.service._zmq import load_curve_keys

__all__ = ["check_config"]


def check_config(
    config: AfmdriftConfig, *, instrument_url: str | None = None
) -> tuple[Predictor, Instrument]:
    """Everything ``run`` needs from ``config``, built but not started.

    Returns the predictor and the (unconnected) instrument.

    Raises
    ------
    AfmdriftError
        :class:`~afmdrift.errors.ConfigError` for an unknown predictor or term,
        a plugin that cannot be imported, an unusable instrument URL,
        ``closed_loop`` with an instrument that cannot move (``folder:``);
        :class:`~afmdrift.service.ServiceSocketError` for missing CURVE keys.
    """
    predictor = make_predictor(config.model.predictor, config.model)
    load_curve_keys(config.service)
    instrument = open_instrument(config, url=instrument_url)
    if config.service.closed_loop and isinstance(instrument, FolderInstrument):
        url = instrument_url or config.driver.transport
        raise ConfigError(
            f"service.closed_loop = true, but the instrument {url}"
            " is a folder of saved images: it cannot move the scan offset. Set closed_loop = false"
            " and apply the published d(t) with your own controller (docs/instruments.md)."
        )
    return predictor, instrument
