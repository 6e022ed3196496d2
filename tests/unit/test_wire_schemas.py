"""The JSON Schema files in docs/schemas: generated from the wire models, kept
up to date, and satisfied by the messages a running daemon really sends."""

from __future__ import annotations

import asyncio
import json
from pathlib import Path

import jsonschema
import pytest
import zmq
import zmq.asyncio
from service_sim import closed_port, driver, running_service, service_config

from afmdrift.wire import SCHEMA_MODELS, json_schemas

SCHEMA_DIR = Path(__file__).resolve().parents[2] / "docs" / "schemas"


def _validator(name: str) -> jsonschema.Draft202012Validator:
    schema = json.loads((SCHEMA_DIR / f"{name}.schema.json").read_text(encoding="utf-8"))
    jsonschema.Draft202012Validator.check_schema(schema)
    return jsonschema.Draft202012Validator(schema)


def test_schema_files_are_generated_from_the_models() -> None:
    """Regenerate with: python -c "from afmdrift.wire import write_json_schemas as w;
    w('docs/schemas')"."""
    generated = json_schemas()
    assert sorted(p.name for p in SCHEMA_DIR.glob("*.schema.json")) == sorted(
        f"{n}.schema.json" for n in SCHEMA_MODELS
    )
    for name, schema in generated.items():
        on_disk = json.loads((SCHEMA_DIR / f"{name}.schema.json").read_text(encoding="utf-8"))
        assert on_disk == json.loads(json.dumps(schema)), f"docs/schemas/{name} is out of date"


@pytest.mark.asyncio
async def test_real_offset_status_and_control_messages_satisfy_the_schemas(
    tmp_path: Path, ctx: zmq.asyncio.Context
) -> None:
    cfg = service_config(tmp_path / "run")
    async with running_service(cfg, driver(f"socket://127.0.0.1:{closed_port()}"), ctx) as svc:
        sub = ctx.socket(zmq.SUB)
        sub.setsockopt(zmq.LINGER, 0)
        sub.setsockopt(zmq.SUBSCRIBE, b"")
        sub.connect(svc.pub_endpoint)
        seen: dict[str, int] = {"offset": 0, "status": 0}
        try:
            async with asyncio.timeout(10.0):
                while min(seen.values()) < 3:
                    topic, payload = await sub.recv_multipart()
                    name = topic.decode()
                    _validator(name).validate(json.loads(payload))
                    seen[name] += 1
        finally:
            sub.close()
        req = ctx.socket(zmq.REQ)
        req.setsockopt(zmq.LINGER, 0)
        try:
            req.connect(svc.control_endpoint)
            for body in (
                {"v": 1, "cmd": "status"},
                {"v": 1, "cmd": "model"},
                {"v": 1, "cmd": "pause"},  # refused: no token
                {"v": 1, "cmd": "nonsense"},
            ):
                valid = _validator("control_request").is_valid(body)
                assert valid == (body["cmd"] != "nonsense")
                await req.send(json.dumps(body).encode())
                reply = json.loads(await asyncio.wait_for(req.recv(), 5.0))
                _validator("control_reply").validate(reply)
        finally:
            req.close()
