"""Link fault injection for the live autopilot: dropped, corrupted, duplicated and reordered
packets, outage windows (no traffic either way), NaN float fields. Deterministic from its RNG.
(FC reboots and sensor dropouts are handled by the autopilot itself.)"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class FaultStats:
    sent: int = 0
    dropped: int = 0
    corrupted: int = 0
    duplicated: int = 0
    reordered: int = 0
    outage_dropped_tx: int = 0
    outage_dropped_rx: int = 0
    nan_fields: int = 0


@dataclass
class LinkFaults:
    cfg: dict
    rng: np.random.Generator
    stats: FaultStats = field(default_factory=FaultStats)
    _held: bytes | None = None

    @property
    def active(self) -> bool:
        c = self.cfg
        return any(c[k] > 0 for k in ("drop_rate", "corrupt_rate", "duplicate_rate", "reorder_rate", "nan_rate")) \
            or bool(c["outages"])

    def in_outage(self, t_s: float) -> bool:
        return any(a <= t_s < b for a, b in self.cfg["outages"])

    def nan_now(self) -> bool:
        if self.cfg["nan_rate"] > 0 and self.rng.random() < self.cfg["nan_rate"]:
            self.stats.nan_fields += 1
            return True
        return False

    def outbound(self, buf: bytes, t_s: float) -> list[bytes]:
        """Packets to put on the wire now in place of ``buf`` (possibly none, possibly two)."""
        c = self.cfg
        if self.in_outage(t_s):
            self.stats.outage_dropped_tx += 1
            return []
        if c["drop_rate"] > 0 and self.rng.random() < c["drop_rate"]:
            self.stats.dropped += 1
            return []
        if c["corrupt_rate"] > 0 and self.rng.random() < c["corrupt_rate"]:
            b = bytearray(buf)
            for _ in range(int(self.rng.integers(1, 4))):
                i = int(self.rng.integers(0, len(b)))
                b[i] ^= int(self.rng.integers(1, 256))
            buf = bytes(b)
            self.stats.corrupted += 1
        out = [buf]
        if c["duplicate_rate"] > 0 and self.rng.random() < c["duplicate_rate"]:
            out.append(buf)
            self.stats.duplicated += 1
        if self._held is not None:
            out.append(self._held)  # the held packet goes out after this one: reordered
            self._held = None
        elif c["reorder_rate"] > 0 and self.rng.random() < c["reorder_rate"]:
            self._held = out.pop(0)
            self.stats.reordered += 1
        self.stats.sent += len(out)
        return out
