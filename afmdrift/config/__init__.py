"""The configuration: one pydantic root model, loaded from TOML.

Part of the ground floor: every layer may import it, so it imports none of
them. Each section (``registration``, ``driver``, ``model``, ``service``) has
its own module here, and the package it configures re-exports it
(``afmdrift.registration.RegistrationConfig``, ...). This module assembles them
into :class:`AfmdriftConfig`, rejects unknown keys and out-of-range values, and
turns pydantic's errors into messages that name the key, the value and the
allowed range.
"""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any, Literal, get_args, get_origin

import annotated_types
from pydantic import BaseModel, ConfigDict, Field, ValidationError
from pydantic.fields import FieldInfo

from afmdrift._bounded import read_text
from afmdrift.config._driver import FOLDER_PREFIX, NANONIS_PREFIX, REPLAY_PREFIX, DriverConfig
from afmdrift.config._model import KalmanConfig, ModelConfig, NNConfig, PhysicsConfig
from afmdrift.config._registration import RegistrationConfig
from afmdrift.config._service import (
    ServiceConfig,
    check_endpoint,
    endpoint_is_local,
    host_is_loopback,
)
from afmdrift.errors import ConfigError

__all__ = [
    "DEFAULT_CONFIG_PATH",
    "FOLDER_PREFIX",
    "MAX_CONFIG_BYTES",
    "NANONIS_PREFIX",
    "REPLAY_PREFIX",
    "AfmdriftConfig",
    "DriverConfig",
    "KalmanConfig",
    "ModelConfig",
    "NNConfig",
    "PhysicsConfig",
    "RegistrationConfig",
    "ServiceConfig",
    "check_endpoint",
    "describe_validation_error",
    "endpoint_is_local",
    "host_is_loopback",
    "load_config",
    "parse_config",
    "read_toml",
]

#: Largest configuration file read (a configuration is a few kB).
MAX_CONFIG_BYTES = 1 << 20

#: ``config/default.toml`` in a source checkout.
DEFAULT_CONFIG_PATH = Path(__file__).resolve().parents[2] / "config" / "default.toml"


class AfmdriftConfig(BaseModel):
    """Root of the configuration file. Every section is optional."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    registration: RegistrationConfig = Field(default_factory=RegistrationConfig)
    service: ServiceConfig = Field(default_factory=ServiceConfig)
    model: ModelConfig = Field(default_factory=ModelConfig)
    driver: DriverConfig = Field(default_factory=DriverConfig)


def parse_config(data: dict[str, Any], *, source: str = "<config>") -> AfmdriftConfig:
    """Validate a mapping (as read from TOML) into :class:`AfmdriftConfig`.

    Validation is strict, as a file should be read: ``archive_frames = "yes"``,
    ``threads = true`` or ``offset_rate_hz = "100"`` are errors, not coerced;
    an integer is accepted where a float is expected; ``inf`` and ``nan`` are
    rejected everywhere.

    Raises
    ------
    ConfigError
        One line per problem, each naming the dotted key, the value and what is allowed.
    """
    try:
        return AfmdriftConfig.model_validate(data, strict=True)
    except ValidationError as err:
        raise ConfigError(
            describe_validation_error(err, source=source, root=AfmdriftConfig)
        ) from None


def describe_validation_error(err: ValidationError, *, source: str, root: type[BaseModel]) -> str:
    """One line per problem of ``err``, naming the dotted key, the value and the allowed range.

    ``root`` is the model that was validated; any pydantic model built like the
    configuration (nested models, ``extra="forbid"``, ``Field`` ranges) works,
    e.g. the simulator's scenario files.
    """
    return "\n".join(_describe_error(e, source, root) for e in err.errors())


def load_config(path: str | Path | None = None) -> AfmdriftConfig:
    """Read and validate a TOML configuration file (default: ``config/default.toml``)."""
    if path is None:
        if not DEFAULT_CONFIG_PATH.is_file():
            return AfmdriftConfig()
        path = DEFAULT_CONFIG_PATH
    p = Path(path)
    return parse_config(read_toml(p, what="configuration file"), source=str(p))


def read_toml(path: str | Path, *, what: str, max_bytes: int = MAX_CONFIG_BYTES) -> dict[str, Any]:
    """Read a TOML file with limits: a regular file, at most ``max_bytes``, UTF-8.

    A FIFO, a device (``/dev/zero``), a directory, an oversized or non-UTF-8
    file, or TOML nested too deeply for the parser gives one clear
    :class:`ConfigError` naming the file, never a hang or a traceback.
    """
    p = Path(path)
    try:
        text = read_text(p, max_bytes=max_bytes, what=what)
    except FileNotFoundError:
        raise ConfigError(f"{p}: {what} not found") from None
    except ValueError as err:
        raise ConfigError(f"{p}: {err}") from None
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(f"{p}: not valid TOML: {err}") from None
    except RecursionError:
        raise ConfigError(f"{p}: TOML nested too deeply") from None


def _describe_error(error: Any, source: str, root: type[BaseModel]) -> str:
    loc = tuple(error["loc"])
    key = ".".join(str(part) for part in loc)
    kind = error["type"]
    value = error.get("input")
    if not loc:  # a check across several keys of the root table
        return f"{source}: {error['msg']}"
    if kind == "extra_forbidden":
        allowed = _allowed_keys(loc[:-1], root)
        hint = f" (allowed keys: {', '.join(allowed)})" if allowed else ""
        return f"{source}: unknown key '{key}'{hint}"
    field = _field_at(loc, root)
    allowed_range = _allowed_range(field) if field is not None else ""
    shown = repr(value) if not isinstance(value, dict) else "a table"
    msg = f"{source}: {key} = {shown}: {error['msg']}"
    if allowed_range:
        msg += f" (allowed: {allowed_range})"
    return msg


def _model_at(loc: tuple[Any, ...], root: type[BaseModel]) -> type[BaseModel] | None:
    model: type[BaseModel] = root
    for part in loc:
        if isinstance(part, int):  # index into an array of tables: stay on its model
            continue
        info = model.model_fields.get(str(part))
        if info is None:
            return None
        # A nested table may be optional (``Section | None``) or a list of tables.
        candidates = [info.annotation, *get_args(info.annotation)]
        sub = [a for a in candidates if isinstance(a, type) and issubclass(a, BaseModel)]
        if not sub:
            return None
        model = sub[0]
    return model


def _allowed_keys(loc: tuple[Any, ...], root: type[BaseModel]) -> list[str]:
    model = _model_at(loc, root)
    return sorted(model.model_fields) if model is not None else []


def _field_at(loc: tuple[Any, ...], root: type[BaseModel]) -> FieldInfo | None:
    if not loc:
        return None
    model = _model_at(loc[:-1], root)
    if model is None:
        return None
    return model.model_fields.get(str(loc[-1]))


def _allowed_range(field: FieldInfo) -> str:
    bounds: list[str] = []
    for meta in field.metadata:
        if isinstance(meta, annotated_types.Ge):
            bounds.append(f">= {meta.ge}")
        elif isinstance(meta, annotated_types.Gt):
            bounds.append(f"> {meta.gt}")
        elif isinstance(meta, annotated_types.Le):
            bounds.append(f"<= {meta.le}")
        elif isinstance(meta, annotated_types.Lt):
            bounds.append(f"< {meta.lt}")
    if bounds:
        return " and ".join(bounds)
    ann = field.annotation
    literal_values = _literal_values(ann)
    if literal_values:
        return "one of " + ", ".join(repr(v) for v in literal_values)
    return ""


def _literal_values(ann: Any) -> list[Any]:
    if get_origin(ann) is Literal:
        return list(get_args(ann))
    values: list[Any] = []
    for arg in get_args(ann):
        values.extend(_literal_values(arg))
    return values
