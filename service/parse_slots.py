"""The API process's upload-reading slots, shared fairly between API keys (:class:`FairSlots`).

Reading and parsing an upload hold one of ``max_concurrent_parses`` slots (:func:`service.submission.parse_slot`).
Taken in order of arrival alone, two slow uploads of one key would hold them all and every other key's uploads,
however small, would wait and be refused ``busy``; so a key holds at most all slots but one, and a freed slot goes
to the waiting key that holds the fewest.
"""

from __future__ import annotations

import itertools
import threading
from collections import Counter


class FairSlots:
    """``capacity`` slots shared between owners (API keys, or client addresses when the server has no keys).

    An owner holds at most :attr:`per_owner` slots at once (all but one when there are two or more, so one owner
    never takes the last), and a freed slot goes to the waiter whose owner holds the fewest, the earliest among
    equals.
    """

    def __init__(self, capacity: int):
        self.capacity = capacity
        self.per_owner = max(1, capacity - 1)
        self._cond = threading.Condition()
        self._held: Counter[str] = Counter()
        self._waiting: list[tuple[str, int]] = []  # (owner, ticket), in order of arrival
        self._tickets = itertools.count()

    def held(self, owner: str | None = None) -> int:
        """Slots held now by ``owner`` (by everyone when None)."""
        with self._cond:
            return self._held[owner] if owner is not None else sum(self._held.values())

    def _turn(self, owner: str, ticket: int) -> bool:
        if sum(self._held.values()) >= self.capacity or self._held[owner] >= self.per_owner:
            return False
        first = min((self._held[o], i, t) for i, (o, t) in enumerate(self._waiting) if self._held[o] < self.per_owner)
        return first[2] == ticket

    def acquire(self, owner: str, timeout: float | None = None) -> bool:
        """Take a slot for ``owner`` once it is its turn; False when that did not come within ``timeout`` seconds."""
        with self._cond:
            ticket = next(self._tickets)
            self._waiting.append((owner, ticket))
            try:
                got = self._cond.wait_for(lambda: self._turn(owner, ticket), timeout)
                if got:
                    self._held[owner] += 1
                return got
            finally:
                self._waiting.remove((owner, ticket))
                self._cond.notify_all()  # the next waiter's turn may have come

    def release(self, owner: str) -> None:
        """Give back a slot ``owner`` holds."""
        with self._cond:
            self._held[owner] -= 1
            if self._held[owner] <= 0:
                del self._held[owner]
            self._cond.notify_all()
