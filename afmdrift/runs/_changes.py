"""Changes of a run's model: an effect term added or removed, a model reloaded.

A daemon's model can change while it runs (the control commands
``add_term``, ``remove_term`` and ``reload_model``, ``docs/service.md``).
Each change is a :class:`ModelChange` in the run store's ``model_changes``
table, so the tools that read the run know where the model changed, and a
daemon restarted on the same run directory applies the run's term changes to
its configuration again (:func:`effective_model`): an added term belongs to
the run, and the configuration file is never rewritten.

A term given to ``add_term`` is checked by building the predictor with it,
exactly as ``afmdrift config check`` builds the configured one
(:func:`afmdrift.model.make_predictor`), so the two never disagree on what
a valid term is.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Sequence
from typing import Literal

from afmdrift.config import ModelConfig
from afmdrift.errors import ConfigError
from afmdrift.model import Predictor, make_predictor

__all__ = [
    "PHYSICS_PREDICTORS",
    "TERM_COMMANDS",
    "ModelChange",
    "TermCommand",
    "change_terms",
    "effective_model",
    "model_terms",
]

log = logging.getLogger(__name__)

TermCommand = Literal["add_term", "remove_term"]
#: The commands that change the terms of the physics model.
TERM_COMMANDS: tuple[TermCommand, ...] = ("add_term", "remove_term")
#: Predictors whose terms are ``[model.physics] terms``.
PHYSICS_PREDICTORS = frozenset({"physics", "physics_nn"})


@dataclasses.dataclass(frozen=True, slots=True)
class ModelChange:
    """One change of a run's model (a row of the ``model_changes`` table).

    Attributes
    ----------
    seq : int
        The last frame processed before the change (-1: before the first);
        the frame ``seq + 1`` is the first the new model predicted.
    t_s : float
        Instrument time of the change, s (NaN when the instrument clock was
        not known yet).
    wall_s : float
        Unix time of the change, s.
    command : str
        ``add_term``, ``remove_term`` or ``reload_model``.
    term : str or None
        The term added or removed (``None`` for ``reload_model``).
    predictor : str
        The predictor after the change.
    terms_before, terms_after : tuple of str or None
        The physics model's terms before and after (``None`` when that
        predictor is not the physics model).
    handover_until_s : float
        Instrument time at which d(t) reached the new model's prediction
        (NaN: no curve was published yet, so there was nothing to hand over).
    step_bound_nm : float
        The largest step d(t) was allowed between two offset samples during
        the hand-over, max(the prediction's 1σ, 0.5 nm) (NaN as above).
    """

    seq: int
    t_s: float
    wall_s: float
    command: str
    term: str | None
    predictor: str
    terms_before: tuple[str, ...] | None
    terms_after: tuple[str, ...] | None
    handover_until_s: float = math.nan
    step_bound_nm: float = math.nan


def model_terms(model: ModelConfig) -> list[str] | None:
    """The effect terms of ``model``'s predictor (``None`` for one without terms)."""
    if model.predictor not in PHYSICS_PREDICTORS:
        return None
    return list(model.physics.terms)


def change_terms(model: ModelConfig, command: str, term: str) -> tuple[ModelConfig, Predictor]:
    """``model`` with ``term`` added (``add_term``) or removed (``remove_term``),
    and a fresh predictor built from it.

    The new predictor is built as ``afmdrift config check`` builds the
    configured one (:func:`~afmdrift.model.make_predictor`), so a term it
    would refuse is refused here, with the same message.

    Raises
    ------
    ConfigError
        The predictor is not the physics model; the term is empty, does not
        parse or is unknown; it is already a term (``add_term``); it is not a
        term (``remove_term``), or the last one. The message starts with
        ``command`` and names the term.
    """
    if command not in TERM_COMMANDS:
        raise ConfigError(f"{command}: not a term command (known: {', '.join(TERM_COMMANDS)})")
    terms = model_terms(model)
    if terms is None:
        raise ConfigError(
            f"{command}: the predictor is {model.predictor!r}, which has no effect terms; "
            f"terms belong to the physics model ([model] predictor = "
            f"{' or '.join(map(repr, sorted(PHYSICS_PREDICTORS)))})"
        )
    name = term.strip()
    if not name:
        raise ConfigError(f"{command}: needs a term (a name or a term spec, docs/model.md)")
    if command == "add_term":
        if name in terms:
            raise ConfigError(f"add_term: {name!r} is already a term of the model ({terms})")
        after = [*terms, name]
    else:
        if name not in terms:
            raise ConfigError(f"remove_term: {name!r} is not a term of the model ({terms})")
        if len(terms) == 1:
            raise ConfigError(f"remove_term: {name!r} is the model's only term; it stays")
        after = [t for t in terms if t != name]
    physics = model.physics.model_copy(update={"terms": after})
    new = model.model_copy(update={"physics": physics})
    try:
        predictor = make_predictor(new.predictor, new)
    except ConfigError as err:
        raise ConfigError(f"{command} {name!r}: {err}") from None
    return new, predictor


def effective_model(model: ModelConfig, changes: Sequence[ModelChange]) -> ModelConfig:
    """``model`` (the configuration's) with a run's term changes applied again.

    The ``add_term`` and ``remove_term`` changes after the run's last
    ``reload_model`` (which took the terms of a file) are applied in order.
    One that no longer applies (the configuration has the term already, or
    lacks it, or another predictor; a plugin that is gone) is skipped with a
    warning: the configuration file is never rewritten, so it may have been
    edited since.
    """
    last_reload = max((i for i, c in enumerate(changes) if c.command == "reload_model"), default=-1)
    for change in changes[last_reload + 1 :]:
        if change.command not in TERM_COMMANDS or change.term is None:
            continue
        try:
            model, _ = change_terms(model, change.command, change.term)
        except ConfigError as err:
            log.warning("the run's model change after frame %d is skipped: %s", change.seq, err)
    return model
