"""One history feed: channels and events reach the models in time order.

The daemon, ``afmdrift replay``, ``afmdrift evaluate`` and ``afmdrift
diagnose`` all give a model the channel samples and event-log entries logged
up to the time it is asked about, and nothing later. :class:`HistoryFeed` is
that rule, written once: entries are pushed as they become known (all at once
for a recorded session or a run store, as they arrive for a live instrument),
and :meth:`HistoryFeed.advance` moves those logged at or before a time into the
:class:`~afmdrift.model.History` that the models read.
"""

from __future__ import annotations

import logging
import math
from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass

from afmdrift.model._base import History
from afmdrift.records import ChannelSample, Event, LoggedEvent

__all__ = ["FeedBatch", "HistoryFeed"]

log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class FeedBatch:
    """What one :meth:`HistoryFeed.advance` added to the history."""

    channels: list[ChannelSample]
    events: list[LoggedEvent]


class HistoryFeed:
    """Pending channel samples and events, released into :attr:`history` by time.

    Parameters
    ----------
    channels : iterable of ChannelSample, optional
        Samples in the order they were logged.
    events : iterable of Event or LoggedEvent, optional
        Event-log entries; a bare :class:`Event` gets epoch 0 and the next log
        index.

    Notes
    -----
    A channel sample older than the last one released is dropped with a
    warning: the models' channel log only grows forward in time.
    """

    def __init__(
        self,
        channels: Iterable[ChannelSample] = (),
        events: Iterable[Event | LoggedEvent] = (),
    ) -> None:
        self.history = History()
        self._channels: deque[ChannelSample] = deque()
        self._events: list[LoggedEvent] = []
        self._next_index = 0
        self.push(channels, events)

    def push(
        self,
        channels: Iterable[ChannelSample] = (),
        events: Iterable[Event | LoggedEvent] = (),
    ) -> None:
        """Make entries known; they reach the history at the next :meth:`advance`."""
        self._channels.extend(channels)
        for e in events:
            entry = e if isinstance(e, LoggedEvent) else LoggedEvent(0, self._next_index, e)
            self._next_index = entry.log_index + 1
            self._events.append(entry)
        # Stable by time, so entries logged at the same instant keep log order.
        self._events.sort(key=lambda le: le.event.t_s)

    def advance(self, t_s: float = math.inf) -> FeedBatch:
        """Release every pending entry logged at or before ``t_s``; return them."""
        channels: list[ChannelSample] = []
        while self._channels and self._channels[0].t_s <= t_s:
            sample = self._channels.popleft()
            if self.history.channel_t_s and sample.t_s < self.history.channel_t_s[-1]:
                log.warning("channel sample at t=%.3f s is out of order; dropped", sample.t_s)
                continue
            self.history.add_channels(sample)
            channels.append(sample)
        k = 0
        while k < len(self._events) and self._events[k].event.t_s <= t_s:
            k += 1
        events, self._events = self._events[:k], self._events[k:]
        if events:
            self.history.add_events(e.event for e in events)
        return FeedBatch(channels=channels, events=events)
