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
from afmdrift.drivers import Instrument
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
        a plugin that cannot be imported, an unusable instrument URL;
        :class:`~afmdrift.service.ServiceSocketError` for missing CURVE keys.
    """
    predictor = make_predictor(config.model.predictor, config.model)
    load_curve_keys(config.service)
    instrument = open_instrument(config, url=instrument_url)
    return predictor, instrument
