"""What a registration computes once and reuses, held by whoever owns the clouds (a pair, a run),
never hung on the clouds themselves.

A `CloudMemo` belongs to one prepared cloud in one role (source or target: the coarse stage seeds
each role differently); a `PairMemo` to one (source, target) pair, holding its two clouds' memos.
A run whose scans take part in several pairs keeps them in a `RunMemo`. Every slot holds one value
and the key it was computed for: another key replaces it, so memory stays bounded. A `Shelf` keeps a
value for each of a few keys (a cloud's vertical hypotheses), held in a slot that bounds its life.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable, Hashable
from dataclasses import dataclass, field
from typing import Any


class Slot:
    """One remembered value and the key it was computed for."""

    def __init__(self) -> None:
        self._key: Hashable | None = None
        self._value: Any = None
        self._held = False
        self._lock = threading.RLock()  # the stages' two-thread maps share a pair's memo

    def get(self, key: Hashable, compute: Callable[[], Any]) -> Any:
        """The value for `key`, computed (and kept in place of any other) when it is not held; one
        caller computes it, the others wait for it (a mutable value, the rival table, stays one)."""
        with self._lock:
            if not self._held or self._key != key:
                self._value, self._key, self._held = compute(), key, True
            return self._value


class Shelf:
    """Values by key, each computed once and kept: for a small, fixed set of keys."""

    def __init__(self) -> None:
        self._slots: dict[Hashable, Slot] = {}
        self._lock = threading.Lock()

    def get(self, key: Hashable, compute: Callable[[], Any]) -> Any:
        """The value for `key`, computed on first use; callers of other keys do not wait for it."""
        with self._lock:
            slot = self._slots.setdefault(key, Slot())
        return slot.get(key, compute)


@dataclass(frozen=True, eq=False)
class CloudMemo:
    """Figures of one prepared cloud in one role, each a pure function of the cloud and its key."""

    coarse: Slot = field(default_factory=Slot)  # the coarse stage's sample and its levelled forms
    judge: Slot = field(default_factory=Slot)  # the judge's seeded samples
    scene: Slot = field(default_factory=Slot)  # the scene figures
    scanner: Slot = field(default_factory=Slot)  # the nearest-return image (align/freespace.py)


@dataclass(frozen=True, eq=False)
class PairMemo:
    """What one (source, target) pair computes once: its clouds' memos, the global search (the
    default path's pose and the rivals of a local result are the same search) and the judge's
    refined rivals (every verdict of the pair refines and scores a start once)."""

    source: CloudMemo = field(default_factory=CloudMemo)
    target: CloudMemo = field(default_factory=CloudMemo)
    search: Slot = field(default_factory=Slot)
    rivals: Slot = field(default_factory=Slot)


class RunMemo:
    """The memos of a run whose scans take part in several pairs: one CloudMemo per scan and role
    (the most recent `max_clouds` kept), and per source scan the PairMemo of its latest target."""

    def __init__(self, max_clouds: int = 8) -> None:
        self.max_clouds = max_clouds
        self._clouds: OrderedDict[tuple[Hashable, str], CloudMemo] = OrderedDict()
        self._pairs: OrderedDict[Hashable, tuple[Hashable, PairMemo]] = OrderedDict()

    def cloud(self, scan: Hashable, role: str) -> CloudMemo:
        key = (scan, role)
        memo = self._clouds.pop(key, None) or CloudMemo()
        self._clouds[key] = memo
        while len(self._clouds) > self.max_clouds:
            self._clouds.popitem(last=False)
        return memo

    def pair(self, source: Hashable, target: Hashable) -> PairMemo:
        """The memo of the pair `source` -> `target` (scan keys: equal keys, equal clouds)."""
        src, tgt = self.cloud(source, "source"), self.cloud(target, "target")
        held = self._pairs.pop(source, None)
        if (
            held is None
            or held[0] != target
            or held[1].source is not src
            or held[1].target is not tgt
        ):
            held = (target, PairMemo(src, tgt))
        self._pairs[source] = held
        while len(self._pairs) > self.max_clouds:
            self._pairs.popitem(last=False)
        return held[1]
