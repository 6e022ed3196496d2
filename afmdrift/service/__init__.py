"""The drift service: asyncio daemon, ZeroMQ publisher, durable run store.

Depends only on the driver interface (:mod:`afmdrift.drivers`), never on the
simulator or the test helpers (enforced by import-linter, see pyproject.toml).
"""
