"""Shared fixtures and guards for the whole test suite."""

from __future__ import annotations

import asyncio
import gc
from collections.abc import Iterator
from pathlib import Path

import pytest
import zmq.asyncio

REPO_ROOT = Path(__file__).resolve().parent.parent
REAL_DATA_DIR = REPO_ROOT.parent / "shared" / "data" / "real"


@pytest.fixture
def real_data_dir() -> Path:
    """``../shared/data/real``; tests using it skip with a reason when it is absent."""
    if not REAL_DATA_DIR.is_dir():
        pytest.skip(f"real AFM data folder not found at {REAL_DATA_DIR}")
    return REAL_DATA_DIR


@pytest.fixture
def real_file(real_data_dir: Path):  # type: ignore[no-untyped-def]
    """Return a function that gives the path of a named real-data file or skips."""

    def _get(name: str) -> Path:
        p = real_data_dir / name
        if not p.is_file():
            pytest.skip(f"real AFM file {name} not found in {real_data_dir}")
        return p

    return _get


@pytest.fixture
def ctx() -> Iterator[zmq.asyncio.Context]:
    """A ZeroMQ context of the test's own, terminated after it."""
    context = zmq.asyncio.Context()
    yield context
    context.term()


@pytest.fixture(autouse=True)
def _fail_on_leaked_tasks(request: pytest.FixtureRequest) -> Iterator[None]:
    """Fail any async test that leaves asyncio tasks running on its loop."""
    yield
    if request.node.get_closest_marker("asyncio") is None:
        return
    try:
        loop = asyncio.get_event_loop_policy().get_event_loop()
    except RuntimeError:
        return
    if loop.is_closed():
        return
    pending = [t for t in asyncio.all_tasks(loop) if not t.done()]
    if pending:
        for t in pending:
            t.cancel()
        gc.collect()
        pytest.fail(f"test left {len(pending)} asyncio task(s) running: {pending!r}")
