"""Wire format of the drift service, version 1 (documented in ``docs/wire.md``).

Every message on the PUB socket is a two-part ZeroMQ message
``[topic, payload]``: the topic is one of ``offset``, ``model``, ``frame``,
``status``, ``diagnosis`` (ASCII, used for subscription filtering) and the payload is a UTF-8
JSON object validated by the pydantic schema of that topic. Every payload
carries ``"v"`` (the schema version, :data:`SCHEMA_VERSION`) and ``"topic"``.
A decoder rejects another version with :class:`WireError` instead of guessing.

The control socket (REQ/REP) exchanges single-part JSON messages
(:class:`ControlRequest`, :class:`ControlReply`) with the same version field.

Times: ``t_s`` is the instrument clock (s since the session start), ``wall_s``
the publisher's Unix time (s). Positions and offsets are nm in the
registration sign convention (``README.md``, Conventions).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated, Any, Literal, TypeVar

from pydantic import BaseModel, ConfigDict, Field, TypeAdapter, ValidationError

from afmdrift._bounded import MAX_JSON_DEPTH, loads_json
from afmdrift.errors import AfmdriftError

__all__ = [
    "MAX_JSON_DEPTH",
    "MAX_PAYLOAD_BYTES",
    "SCHEMA_MODELS",
    "SCHEMA_VERSION",
    "STATE_CHANGING",
    "TOPICS",
    "ClockSync",
    "ControlReply",
    "ControlRequest",
    "DiagnosisMsg",
    "FieldSummary",
    "FrameMsg",
    "Message",
    "ModelMsg",
    "OffsetMsg",
    "Published",
    "StatusMsg",
    "TrajectorySample",
    "WireError",
    "control_request",
    "decode",
    "decode_control_reply",
    "decode_control_request",
    "encode",
    "json_schemas",
    "write_json_schemas",
]

#: Version of every schema in this module; bumped on any incompatible change.
SCHEMA_VERSION: Literal[1] = 1

TOPICS: tuple[str, ...] = ("offset", "model", "frame", "status", "diagnosis")


class WireError(AfmdriftError, ValueError):
    """A message does not follow the wire format (topic, version or fields)."""


_M = TypeVar("_M", bound=BaseModel)


class _Msg(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)

    v: Literal[1] = SCHEMA_VERSION


class _Published(_Msg):
    """Fields every PUB message carries besides its topic's own.

    ``seq`` counts this topic's messages from 0; ``run_id`` is new each time
    the daemon starts (its sequence numbers restart with it), ``epoch``
    counts instrument restarts within the run (times stay on one axis).
    """

    run_id: str = Field("", max_length=64)
    epoch: int = Field(0, ge=0)


class _Chained(_Published):
    """``chain`` numbers the chain of drift positions a value belongs to: 0
    for the chain the daemon started (or resumed) in, one more for each new
    registration reference whose position was estimated (a reset, a new scan
    geometry, an instrument restart or another instrument); a scan geometry
    taken up again goes back to its own chain's number. Positions of two
    chains differ by an estimate, not by a measurement. Absent in older
    messages: 0."""

    chain: int = Field(0, ge=0)


class ClockSync(BaseModel):
    """Mapping from the publisher's wall clock to the instrument clock.

    ``t_s = instrument_s + rate * (wall - wall_s)`` for a wall time ``wall``;
    ``rate`` is 1 for a real instrument and the speed-up of an accelerated
    simulator or replay.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    wall_s: float
    instrument_s: float
    rate: float = Field(gt=0)

    def instrument_at(self, wall_s: float) -> float:
        """Instrument time at Unix time ``wall_s``."""
        return self.instrument_s + self.rate * (wall_s - self.wall_s)


class OffsetMsg(_Chained):
    """One sample of the offset stream d(t) (topic ``offset``).

    ``valid`` is false before the first model, while the stream is stale, or
    when the service is paused; ``clamped`` is true when the safety limits
    changed the value; ``chain`` is that of the last frame processed.
    """

    topic: Literal["offset"] = "offset"
    seq: int = Field(ge=0)
    t_s: float
    wall_s: float
    x_nm: float
    y_nm: float
    valid: bool
    clamped: bool = False


class ModelMsg(_Chained):
    """The current model after a frame, or after a change of the model by a
    control command (topic ``model``; then ``frame`` is the last frame
    processed and ``t_s`` the instrument time of the change).

    ``curve`` is ``OffsetCurve.to_dict()``; a subscriber rebuilds it with
    ``afmdrift.model.OffsetCurve.from_dict`` and evaluates d(t) at any time and
    rate (``afmdrift.client.Subscriber.offset_at`` does this). The published
    offset stream additionally applies the safety limits ``max_offset_nm`` and
    ``max_offset_rate_nm_s``, given here so a subscriber can apply them too.
    """

    topic: Literal["model"] = "model"
    seq: int = Field(ge=0)
    frame: int = Field(ge=0)
    t_s: float
    wall_s: float
    predictor: str
    curve: dict[str, Any]
    clock: ClockSync
    max_offset_nm: float
    max_offset_rate_nm_s: float


class FieldSummary(BaseModel):
    """Summary of a frame's block displacement field (nm, over valid blocks)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    total_blocks: int
    valid_blocks: int
    mean_dx_nm: float | None
    mean_dy_nm: float | None
    std_dx_nm: float | None
    std_dy_nm: float | None
    median_confidence: float | None


class TrajectorySample(BaseModel):
    """One sample of the drift trajectory: p at the scan time of one block row
    (same zero and sign as ``x_nm, y_nm``; docs/service.md, ``trajectory.csv``)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    t_s: float
    x_nm: float
    y_nm: float
    sigma_x_nm: float
    sigma_y_nm: float


class FrameMsg(_Chained):
    """One frame's measurement (topic ``frame``).

    ``dx_nm, dy_nm`` is the measured increment, ``x_nm, y_nm`` the drift
    position p (cumulative, commanded offset moves removed); ``pred_*`` is the
    prediction of p for this frame made before it arrived, and
    ``pred_error_nm`` the Euclidean distance between the two. Values that do
    not exist (first frame, failed measurement) are ``null``.
    """

    topic: Literal["frame"] = "frame"
    seq: int = Field(ge=0)
    frame: int = Field(ge=0)
    instrument_frame: int
    t_s: float
    wall_s: float
    dx_nm: float | None
    dy_nm: float | None
    x_nm: float | None
    y_nm: float | None
    sigma_nm: float | None
    valid: bool
    fed_model: bool
    reason: str
    valid_blocks: int
    total_blocks: int
    field: FieldSummary | None
    pred_x_nm: float | None
    pred_y_nm: float | None
    pred_error_nm: float | None
    latency_s: float
    trajectory: list[TrajectorySample] = Field(
        default_factory=list,
        description="The frame's drift trajectory samples (causal), one per block row, in "
        "time order; empty for a reference or a frame that was not measured.",
    )


class StatusMsg(_Published):
    """Heartbeat (topic ``status``).

    ``state`` is ``running``, ``paused``, ``stale`` or ``stopping``. ``flags``
    lists active conditions: ``no_model`` (no curve yet), ``low_confidence``
    (last frame did not feed the model), ``stale`` (no frame for more than
    ``stale_factor`` expected intervals), ``instrument_error`` (an instrument
    operation failed and has not worked since), ``instrument_silent`` (a request
    unanswered, no byte arriving, for more than ``instrument_silence_s``),
    ``instrument_changed`` (the instrument on the connection was found to be
    another one than before in this run: another identity or pixel size;
    raised for the rest of the daemon's run), ``clamped`` (the last offset was
    limited), ``paused``, ``store_error`` (the run store cannot write:
    ``store_problem`` gives the path and the reason; measuring and publishing
    go on, and the frames are held in memory, ``frames_held``, and written
    when it can again) and ``frame_error`` (the last frame's processing
    failed: ``frame_problem``).
    ``dropped_offset_ticks`` counts offset samples skipped since the daemon
    started because its event loop fell more than 50 ms behind
    the offset schedule (the stream then restarts from now instead of
    bursting). ``frames_unstored`` counts frames measured and published but
    let go unstored (held past ``service.store_hold_mb``), ``frames_failed``
    frames whose processing failed, since the daemon started. ``terms``
    lists the effect terms of the physics model in use, those of the
    configuration with the run's ``add_term`` and ``remove_term`` changes
    applied (``null`` when the predictor is not the physics model, or in a
    message of an older daemon). A status
    inside a control reply is a snapshot: its ``seq`` is that of the last
    published heartbeat, so replies never take numbers from the ``status``
    topic.
    """

    topic: Literal["status"] = "status"
    seq: int = Field(ge=0)
    t_s: float | None
    wall_s: float
    state: Literal["starting", "running", "paused", "stale", "stopping"]
    flags: list[str]
    frames: int
    last_frame_t_s: float | None
    expected_frame_interval_s: float | None
    rolling_error_nm: float | None
    rolling_max_error_nm: float | None
    rolling_window: int
    dropped_offset_ticks: int = Field(0, ge=0)
    store_problem: str | None = None
    frames_held: int = Field(0, ge=0)
    frames_unstored: int = Field(0, ge=0)
    frames_failed: int = Field(0, ge=0)
    frame_problem: str | None = None
    terms: list[str] | None = None


class DiagnosisMsg(_Published):
    """A live diagnosis of the daemon's own run (topic ``diagnosis``).

    ``diagnosis`` is the object ``afmdrift diagnose RUN_DIR --json`` prints
    (``docs/diagnostics.md``), made over a consistent copy of the run store
    that held frames ``first_frame`` to ``last_frame``; ``look`` numbers the
    diagnoses of this run from 1 (each is tested at its share of the run's
    false-alarm level, ``diagnosis.thresholds``); ``reason`` is ``every``
    (``service.diagnose_every_frames``) or ``request`` (the ``diagnose``
    control command).
    """

    topic: Literal["diagnosis"] = "diagnosis"
    seq: int = Field(ge=0)
    wall_s: float
    look: int = Field(ge=1)
    first_frame: int = Field(ge=0)
    last_frame: int = Field(ge=0)
    reason: Literal["every", "request"]
    duration_s: float = Field(ge=0)
    diagnosis: dict[str, Any]


Published = OffsetMsg | ModelMsg | FrameMsg | StatusMsg | DiagnosisMsg
Message = Annotated[Published, Field(discriminator="topic")]
_MESSAGE_ADAPTER: TypeAdapter[Published] = TypeAdapter(Message)


class ControlRequest(_Msg):
    """A command on the control socket.

    ``cmd``: ``status`` (reply carries a StatusMsg), ``model`` (reply also
    carries the current ModelMsg, so a late subscriber need not wait a frame
    period for it), ``pause`` (stop feeding
    the model and publishing valid offsets), ``resume``, ``reset_reference``
    (the next frame becomes the registration reference; the drift position
    continues), ``reload_model`` (re-read ``[model]`` from ``config_path`` or
    the daemon's configuration file and refit on the kept history),
    ``add_term`` and ``remove_term`` (add the effect term ``term`` to the
    physics model in use, or take it out, and refit on the kept history; the
    change belongs to the run, ``docs/service.md``). All but ``status``,
    ``model`` and ``diagnose`` change the daemon's state and need ``token``
    (the content of the daemon's token file) unless the daemon runs with
    ``control_auth = false``. ``diagnose`` starts a live diagnosis of the
    run now (the result comes on the ``diagnosis`` topic; the reply's
    ``started`` is false when one is already running); it needs no token: it
    changes nothing the daemon measures or publishes, and at most one runs at
    a time.
    """

    cmd: Literal[
        "status",
        "model",
        "pause",
        "resume",
        "reset_reference",
        "reload_model",
        "add_term",
        "remove_term",
        "diagnose",
    ]
    config_path: str | None = Field(None, max_length=4096)
    term: str | None = Field(None, max_length=1024)
    token: str | None = Field(None, max_length=256)


#: Control commands that change the daemon's state: they need the token.
STATE_CHANGING: frozenset[str] = frozenset(
    {"pause", "resume", "reset_reference", "reload_model", "add_term", "remove_term"}
)


class ControlReply(_Msg):
    """Answer to a :class:`ControlRequest`; ``error`` is set when ``ok`` is false.

    ``started`` (``diagnose`` only): a diagnosis was started by this request.
    """

    ok: bool
    error: str | None = None
    status: StatusMsg | None = None
    model: ModelMsg | None = None
    started: bool | None = None


def encode(msg: Published) -> list[bytes]:
    """``[topic, payload]`` frames of a PUB message."""
    return [msg.topic.encode("ascii"), msg.model_dump_json().encode("utf-8")]


#: Largest payload a decoder parses, bytes (a model message is a few kB, a
#: diagnosis some tens of kB).
MAX_PAYLOAD_BYTES = 1 << 20


def _load_json(payload: bytes, what: str) -> dict[str, Any]:
    """Parse a payload with limits: size, nesting depth, number length, UTF-8."""
    if len(payload) > MAX_PAYLOAD_BYTES:
        raise WireError(
            f"{what}: payload of {len(payload)} bytes; the limit is {MAX_PAYLOAD_BYTES}"
        )
    try:
        doc = loads_json(payload, what=what)
    except ValueError as err:
        raise WireError(str(err)) from None
    if not isinstance(doc, dict):
        raise WireError(f"{what}: payload must be a JSON object, got {type(doc).__name__}")
    version = doc.get("v")
    if version != SCHEMA_VERSION:
        raise WireError(
            f"{what}: schema version {version!r} is not supported (this side speaks "
            f"{SCHEMA_VERSION})"
        )
    return doc


def decode(parts: list[bytes]) -> Published:
    """Validate a received ``[topic, payload]`` message.

    Raises
    ------
    WireError
        Wrong number of parts, unknown topic, topic/payload mismatch, another
        schema version, or fields that do not match the schema.
    """
    if len(parts) != 2:
        raise WireError(f"expected 2 message parts [topic, payload], got {len(parts)}")
    topic = parts[0].decode("ascii", errors="replace")
    if topic not in TOPICS:
        raise WireError(f"unknown topic {topic!r} (known: {', '.join(TOPICS)})")
    doc = _load_json(parts[1], f"topic {topic!r}")
    if doc.get("topic") != topic:
        raise WireError(f"topic {topic!r} carries a payload for topic {doc.get('topic')!r}")
    try:
        return _MESSAGE_ADAPTER.validate_python(doc)
    except ValidationError as err:
        raise WireError(f"topic {topic!r}: invalid payload: {_one_line(err)}") from None


def control_request(**fields: Any) -> ControlRequest:
    """A :class:`ControlRequest` of ``fields``; :class:`WireError` naming the problem."""
    try:
        return ControlRequest.model_validate(fields)
    except ValidationError as err:
        raise WireError(f"control request: {_one_line(err)}") from None


def decode_control_request(payload: bytes) -> ControlRequest:
    """Validate a control request; raise :class:`WireError` naming the problem."""
    return _decode_control(payload, ControlRequest, "control request")


def decode_control_reply(payload: bytes) -> ControlReply:
    """Validate a control reply; raise :class:`WireError` naming the problem."""
    return _decode_control(payload, ControlReply, "control reply")


def _decode_control(payload: bytes, model: type[_M], what: str) -> _M:
    doc = _load_json(payload, what)
    try:
        return model.model_validate(doc)
    except ValidationError as err:
        raise WireError(f"{what}: {_one_line(err)}") from None


def _one_line(err: ValidationError) -> str:
    """Every problem of ``err`` on one line: ``field: message; ...``."""
    return "; ".join(
        f"{'.'.join(str(part) for part in e['loc']) or 'message'}: {e['msg']}" for e in err.errors()
    )


#: JSON Schema of every message, by the file name it is published under in
#: ``docs/schemas/`` (``<name>.schema.json``).
SCHEMA_MODELS: dict[str, type[BaseModel]] = {
    "offset": OffsetMsg,
    "model": ModelMsg,
    "frame": FrameMsg,
    "status": StatusMsg,
    "diagnosis": DiagnosisMsg,
    "control_request": ControlRequest,
    "control_reply": ControlReply,
}


def json_schemas() -> dict[str, dict[str, Any]]:
    """The JSON Schema (draft 2020-12) of every message, generated from the models.

    ``docs/schemas/<name>.schema.json`` holds them for clients in other
    languages; a test keeps the files equal to this.
    """
    out: dict[str, dict[str, Any]] = {}
    for name, model in SCHEMA_MODELS.items():
        schema = model.model_json_schema(mode="serialization")
        schema["$schema"] = "https://json-schema.org/draft/2020-12/schema"
        schema["$id"] = f"afmdrift/wire/v{SCHEMA_VERSION}/{name}.schema.json"
        out[name] = schema
    return out


def write_json_schemas(directory: str | Path) -> list[Path]:
    """Write :func:`json_schemas` as ``<name>.schema.json`` files into ``directory``."""
    root = Path(directory)
    root.mkdir(parents=True, exist_ok=True)
    paths = []
    for name, schema in json_schemas().items():
        path = root / f"{name}.schema.json"
        path.write_text(json.dumps(schema, indent=2, sort_keys=True) + "\n", encoding="utf-8")
        paths.append(path)
    return paths
