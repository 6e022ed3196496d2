"""The one history feed (afmdrift.model.HistoryFeed) that every tool uses."""

from __future__ import annotations

import math

import pytest

from afmdrift.model import HistoryFeed
from afmdrift.records import ChannelSample, Event, EventKind, LoggedEvent


def _sample(t_s: float, temp_c: float) -> ChannelSample:
    return ChannelSample(t_s=t_s, values={"temperature_c": temp_c})


def test_advance_releases_only_what_was_logged_up_to_the_time() -> None:
    feed = HistoryFeed(
        [_sample(1.0, 20.0), _sample(2.0, 21.0), _sample(3.0, 22.0)],
        [Event(2.5, EventKind.OFFSET_MOVE, 1.0, 0.0), Event(0.5, EventKind.TIP_CHANGE)],
    )
    batch = feed.advance(2.0)
    assert [c.t_s for c in batch.channels] == [1.0, 2.0]
    assert [e.event.t_s for e in batch.events] == [0.5]
    assert feed.history.channel_t_s == [1.0, 2.0]
    assert feed.history.channel_at("temperature_c", 5.0) == pytest.approx(21.0)
    assert [e.t_s for e in feed.history.events] == [0.5]
    later = feed.advance()
    assert [c.t_s for c in later.channels] == [3.0]
    assert [e.event.t_s for e in later.events] == [2.5]
    assert feed.advance(math.inf).channels == []


def test_bare_events_get_log_indices_in_push_order() -> None:
    """A recorded session's events are epoch 0, indexed in file order, released by time."""
    feed = HistoryFeed(events=[Event(3.0, EventKind.TIP_CHANGE), Event(1.0, EventKind.POWER_ON)])
    batch = feed.advance()
    assert batch.events == [
        LoggedEvent(0, 1, Event(1.0, EventKind.POWER_ON)),
        LoggedEvent(0, 0, Event(3.0, EventKind.TIP_CHANGE)),
    ]


def test_logged_events_keep_their_epoch_and_index() -> None:
    feed = HistoryFeed()
    feed.push(events=[LoggedEvent(2, 7, Event(4.0, EventKind.MANIPULATION, 3.0, 4.0))])
    feed.push(events=[Event(5.0, EventKind.TIP_CHANGE)])
    batch = feed.advance(10.0)
    assert [(e.epoch, e.log_index) for e in batch.events] == [(2, 7), (0, 8)]


def test_out_of_order_channel_sample_is_dropped_not_raised() -> None:
    """Regression: a late sample older than the model's log must not stop the pipeline."""
    feed = HistoryFeed([_sample(2.0, 20.0)])
    feed.advance(2.0)
    feed.push([_sample(1.5, 99.0), _sample(3.0, 21.0)])
    batch = feed.advance(3.0)
    assert [c.t_s for c in batch.channels] == [3.0]
    assert feed.history.channel_t_s == [2.0, 3.0]


def test_entries_pushed_later_wait_for_a_later_advance() -> None:
    """The daemon's arrivals: a sample logged after the frame's end waits for the next frame."""
    feed = HistoryFeed()
    feed.push([_sample(10.0, 20.0), _sample(12.0, 20.5)])
    assert [c.t_s for c in feed.advance(11.0).channels] == [10.0]
    assert [c.t_s for c in feed.advance(12.0).channels] == [12.0]
