"""Client of the drift service: subscribe to offsets and models, send control commands.

Example
-------
>>> async def follow() -> None:  # doctest: +SKIP
...     async with subscribe("tcp://127.0.0.1:5560") as sub:
...         async for msg in sub:
...             if msg.topic == "model":
...                 print(sub.offset_at())   # d(now) from the latest model
"""

from afmdrift.client._subscriber import (
    ClientError,
    ControlRefusedError,
    CurveClientKeys,
    NoModelError,
    Subscriber,
    control,
    subscribe,
)

__all__ = [
    "ClientError",
    "ControlRefusedError",
    "CurveClientKeys",
    "NoModelError",
    "Subscriber",
    "control",
    "subscribe",
]
