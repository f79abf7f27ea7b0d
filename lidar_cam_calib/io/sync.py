"""Approximate-time matching of several message streams (ROS-free, deterministic).

Used live (callbacks push messages as they arrive) and in bag replay (records
pushed in log-time order).  Given the same sequence of ``push`` calls the
output is always the same.

Matching rule
-------------
Each topic has a queue sorted by stamp.  Whenever every queue is non-empty,
the *heads* (oldest item of each topic) are examined:

1. If the spread ``max(head) - min(head)`` exceeds ``slop_s``, the oldest head
   can never be matched (every other topic's candidates are newer than its
   head), so it is discarded (``dropped_unmatched``) and the loop repeats.
2. If the spread is within ``slop_s`` but the oldest head's topic already has
   a second queued item that would give a strictly smaller spread with the
   other heads, the oldest head is discarded in favour of it (better pairing).
3. Otherwise the heads are emitted as one set (ordered as ``topics``) and
   removed from their queues.

So a set is emitted as soon as the data that has arrived supports it; choose
``slop_s`` below half the period of the fastest stream to get unambiguous
nearest-neighbour sets.
"""
from __future__ import annotations

import bisect
from typing import Any, Hashable

from .convert import stamp_to_s

__all__ = ["ApproxTimeSync"]


class ApproxTimeSync:
    """Group one item per topic whose stamps lie within ``slop_s`` seconds.

    Parameters
    ----------
    topics:
        Topic names (any hashables); output tuples follow this order.
    slop_s:
        Maximum allowed ``max(stamp) - min(stamp)`` inside a set, seconds.
    queue_size:
        Maximum queued items per topic; on overflow the oldest is dropped
        (``dropped_overflow``).

    Counters: ``emitted``, ``dropped_out_of_order`` (stamp not newer than this
    topic's item in the last emitted set, or than anything already discarded
    for that topic; duplicates of a queued stamp count here too),
    ``dropped_unmatched`` (items discarded because no set could contain
    them), ``dropped_overflow``.
    """

    def __init__(self, topics: list[Hashable], slop_s: float, queue_size: int = 30):
        if len(topics) == 0:
            raise ValueError("ApproxTimeSync needs at least one topic")
        if len(set(topics)) != len(topics):
            raise ValueError(f"duplicate topics in {list(topics)}")
        if not slop_s >= 0:
            raise ValueError(f"slop_s must be >= 0, got {slop_s}")
        if queue_size < 1:
            raise ValueError(f"queue_size must be >= 1, got {queue_size}")
        self.topics = list(topics)
        self.slop_s = float(slop_s)
        self.queue_size = int(queue_size)
        self._index = {t: i for i, t in enumerate(self.topics)}
        self.reset()

    def reset(self) -> None:
        """Forget all queued items, watermarks and counters."""
        self._stamps: list[list[float]] = [[] for _ in self.topics]
        self._items: list[list[Any]] = [[] for _ in self.topics]
        # Per-topic watermark: stamps <= this are refused (already emitted or discarded past).
        self._floor: list[float] = [float("-inf")] * len(self.topics)
        self.emitted = 0
        self.dropped_out_of_order = 0
        self.dropped_unmatched = 0
        self.dropped_overflow = 0
        self.last_set_stamps: tuple[float, ...] | None = None

    def pending(self) -> dict[Hashable, int]:
        """Number of queued items per topic."""
        return {t: len(self._stamps[i]) for i, t in enumerate(self.topics)}

    def push(self, topic: Hashable, stamp_s: float, item: Any) -> list[tuple]:
        """Queue ``item`` stamped ``stamp_s`` (seconds) on ``topic``; return newly complete sets.

        Each returned tuple holds one item per topic in ``topics`` order; an
        item is returned at most once.  ``stamp_s`` may also be a
        builtin_interfaces Time.
        """
        try:
            k = self._index[topic]
        except KeyError:
            raise ValueError(f"unknown topic {topic!r}; expected one of {self.topics}") from None
        t = stamp_to_s(stamp_s)
        if t <= self._floor[k]:
            self.dropped_out_of_order += 1
            return []
        stamps, items = self._stamps[k], self._items[k]
        pos = bisect.bisect_left(stamps, t)
        if pos < len(stamps) and stamps[pos] == t:
            self.dropped_out_of_order += 1  # duplicate stamp on the same topic
            return []
        stamps.insert(pos, t)
        items.insert(pos, item)
        if len(stamps) > self.queue_size:
            self._discard_head(k)
            self.dropped_overflow += 1
        return self._match()

    def _discard_head(self, k: int) -> None:
        self._floor[k] = max(self._floor[k], self._stamps[k][0])
        del self._stamps[k][0]
        del self._items[k][0]

    def _match(self) -> list[tuple]:
        out: list[tuple] = []
        n = len(self.topics)
        while all(self._stamps[k] for k in range(n)):
            heads = [self._stamps[k][0] for k in range(n)]
            lo = min(heads)
            hi = max(heads)
            m = heads.index(lo)  # lowest topic index on ties: deterministic
            if hi - lo > self.slop_s:
                self._discard_head(m)
                self.dropped_unmatched += 1
                continue
            if len(self._stamps[m]) > 1:
                alt = heads.copy()
                alt[m] = self._stamps[m][1]
                if max(alt) - min(alt) < hi - lo:
                    self._discard_head(m)
                    self.dropped_unmatched += 1
                    continue
            items = tuple(self._items[k][0] for k in range(n))
            for k in range(n):
                self._discard_head(k)
            self.emitted += 1
            self.last_set_stamps = tuple(heads)
            out.append(items)
        return out
