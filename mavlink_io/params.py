"""Reading named FC parameters: PARAM_REQUEST_READ for each, resent for the ones not answered.

The daemon needs a few of the FC's parameters to decide what it may send (docs/OUTPUTS.md 1.5: is
EKF2 running, which EKF3 sources take external nav, does the FC's yaw come from our ODOMETRY).
PARAM_REQUEST_READ has no ACK: the answer is a PARAM_VALUE with the name. The names go out together
(ArduPilot queues parameter requests and answered twelve at once in SITL); the ones without an
answer after ``timeout_s`` are asked again, up to ``max_tries`` times, then reported missing (an
unknown name: ArduPilot does not answer one that does not exist, e.g. EK2_ENABLE on a build without
EKF2).

Pure state machine: the caller passes the time, sends the names ``start``/``poll`` return, and
hands every PARAM_VALUE to ``on_value``.
"""
from __future__ import annotations

from dataclasses import dataclass, field


@dataclass(slots=True)
class ParamReader:
    timeout_s: float = 1.0
    max_tries: int = 3
    values: dict = field(default_factory=dict)
    """Name -> value of every watched parameter seen (answers and unsolicited PARAM_VALUEs)."""
    missing: set = field(default_factory=set)
    """Names asked ``max_tries`` times without an answer."""
    _wanted: set = field(default_factory=set)
    _pending: dict = field(default_factory=dict)
    """Name -> tries so far, for names not answered yet."""
    _sent_at_s: float | None = None

    def start(self, names, now_s: float) -> list[str]:
        """Ask for ``names`` (forgetting earlier values: after an FC reboot they may have changed)."""
        self._wanted = set(names)
        self.values = {}
        self.missing = set()
        self._pending = {n: 1 for n in self._wanted}
        self._sent_at_s = now_s
        return sorted(self._pending)

    @property
    def done(self) -> bool:
        """Every name answered or given up."""
        return bool(self._wanted) and not self._pending

    def on_value(self, name: str, value: float) -> bool:
        """A PARAM_VALUE; True when it is one of the watched names (its value may have changed)."""
        if name not in self._wanted:
            return False
        self.values[name] = value
        self._pending.pop(name, None)
        self.missing.discard(name)
        return True

    def next_due_s(self) -> float | None:
        if not self._pending or self._sent_at_s is None:
            return None
        return self._sent_at_s + self.timeout_s

    def poll(self, now_s: float) -> list[str]:
        """Names to ask again now (empty while waiting); gives up on names after ``max_tries``."""
        due = self.next_due_s()
        if due is None or now_s < due:
            return []
        again = []
        for name, tries in list(self._pending.items()):
            if tries >= self.max_tries:
                del self._pending[name]
                self.missing.add(name)
            else:
                self._pending[name] = tries + 1
                again.append(name)
        self._sent_at_s = now_s
        return sorted(again)
