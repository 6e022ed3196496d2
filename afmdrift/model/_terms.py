"""Effect terms by name: the library, entry points, plugins and generic term specs.

A name in ``[model.physics] terms`` (or ``--effects``) is a library term
(:data:`~afmdrift.model._effects.LIBRARY`), a term a package registers under
the entry-point group :data:`ENTRY_POINT_GROUP`, a class named in
``[model.physics] plugins`` (``"package.module:Class"``, see
``docs/effects-plugins.md``), or a generic term spec such as
``channel:pressure_hpa`` (:mod:`afmdrift.model._families`). This module
finds the class of each; it is the one place that knows all four, so the
library and the generic families need not know each other's lookup.
"""

from __future__ import annotations

import importlib
import logging
from collections.abc import Iterable, Mapping
from importlib.metadata import entry_points

from afmdrift.errors import ConfigError
from afmdrift.model._effects import LIBRARY, EffectTerm
from afmdrift.model._families import is_term_spec, parse_term_spec

__all__ = [
    "ENTRY_POINT_GROUP",
    "available_terms",
    "load_term_class",
    "make_term",
    "resolve_terms",
    "term_class",
]

_log = logging.getLogger(__name__)


#: Entry-point group under which third-party packages register effect terms.
ENTRY_POINT_GROUP = "afmdrift.effects"


def load_term_class(spec: str) -> type[EffectTerm]:
    """Import an :class:`EffectTerm` subclass from ``"package.module:Class"``.

    Raises
    ------
    ConfigError
        If the module cannot be imported, has no such attribute, or it is not
        an :class:`EffectTerm` subclass.
    """
    module_name, sep, attr = spec.partition(":")
    if not sep or not module_name or not attr:
        raise ConfigError(f"effect plugin {spec!r}: expected 'package.module:ClassName'")
    try:
        module = importlib.import_module(module_name)
    except ImportError as err:
        raise ConfigError(f"effect plugin {spec!r}: cannot import {module_name!r}: {err}") from None
    except (Exception, SystemExit) as err:
        # A plugin is operator code: whatever its import raises (even
        # sys.exit) is a configuration error, never the end of the daemon.
        raise ConfigError(
            f"effect plugin {spec!r}: importing {module_name!r} raised {type(err).__name__}: {err}"
        ) from None
    obj = getattr(module, attr, None)
    if obj is None:
        raise ConfigError(f"effect plugin {spec!r}: module {module_name!r} has no {attr!r}")
    if not (isinstance(obj, type) and issubclass(obj, EffectTerm)):
        raise ConfigError(f"effect plugin {spec!r}: {attr!r} is not an EffectTerm subclass")
    if not isinstance(getattr(obj, "name", None), str):
        raise ConfigError(f"effect plugin {spec!r}: the class must set a string 'name'")
    return obj


def available_terms(plugins: Iterable[str] = ()) -> dict[str, type[EffectTerm]]:
    """All known terms by name: the library, entry points, then ``plugins`` specs.

    A plugin may not reuse a library name (that would silently change the
    meaning of a configuration).
    """
    terms = dict(LIBRARY)
    for ep in entry_points(group=ENTRY_POINT_GROUP):
        try:
            cls = load_term_class(ep.value)
        except ConfigError as err:
            _log.warning("ignoring entry point %s in %s: %s", ep.name, ENTRY_POINT_GROUP, err)
            continue
        _add(terms, cls, f"entry point {ep.name!r}")
    for spec in plugins:
        _add(terms, load_term_class(spec), f"plugin {spec!r}")
    return terms


def _add(terms: dict[str, type[EffectTerm]], cls: type[EffectTerm], where: str) -> None:
    if cls.name in LIBRARY and LIBRARY[cls.name] is not cls:
        raise ConfigError(f"{where}: term name {cls.name!r} is taken by the built-in library")
    terms[cls.name] = cls


def make_term(name: str, plugins: Iterable[str] = ()) -> EffectTerm:
    """Instantiate the term called ``name`` (library, entry points, ``plugins``, or a
    generic term spec such as ``channel:pressure_hpa``, see ``docs/model.md``)."""
    return term_class(name, available_terms(plugins))()


def term_class(name: str, known: Mapping[str, type[EffectTerm]]) -> type[EffectTerm]:
    """The class of term ``name``: a generic spec, or a name in ``known``.

    Raises
    ------
    ConfigError
        A malformed spec, or a name neither a spec nor known (the message
        lists the known names and the spec syntax).
    """
    if is_term_spec(name):
        return parse_term_spec(name.strip())
    if name not in known:
        raise ConfigError(
            f"unknown effect term {name!r} (known: {', '.join(sorted(known))}; or a generic "
            "term 'channel:<channel>', 'event:<kind>', 'periodic:period_s=<s>', 'jump:t_s=<s>' "
            "or 'rate_change:t_s=<s>', see docs/model.md)"
        )
    return known[name]


def resolve_terms(
    names: Iterable[str], plugins: Iterable[str] = (), *, key: str = "model.physics.terms"
) -> list[type[EffectTerm]]:
    """The term classes of ``names`` (library, entry points, ``plugins`` or specs).

    Raises
    ------
    ConfigError
        Unknown names, malformed specs or duplicates; the message starts with ``key``.
    """
    names = list(names)
    known = available_terms(plugins)
    out: list[type[EffectTerm]] = []
    unknown = [n for n in names if not is_term_spec(n) and n not in known]
    if unknown:
        raise ConfigError(
            f"{key}: unknown term(s) {', '.join(map(repr, unknown))} "
            f"(known: {', '.join(sorted(known))}; or a generic term 'channel:<channel>', "
            "'event:<kind>', 'periodic:period_s=<s>', 'jump:t_s=<s>' or 'rate_change:t_s=<s>', "
            "see docs/model.md)"
        )
    bad: list[str] = []
    for n in names:
        try:
            out.append(term_class(n, known))
        except ConfigError as err:
            bad.append(str(err))
    if bad:
        raise ConfigError(f"{key}: {'; '.join(bad)}")
    if len(set(names)) != len(names):
        raise ConfigError(f"{key}: duplicate names in {names}")
    return out
