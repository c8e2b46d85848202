"""The dashboard's state and its fan-out to browsers.

Zenoh callbacks (``on_sample``, ``on_liveliness``) update a ``WatchState`` (the same store and the
same GONE rule as ``azimuthd watch``) plus each vehicle's dead-reckoned track, and put one JSON
message per sample on every connected browser's queue. A queue is bounded: a browser that does
not keep up loses its oldest messages (counted), never the Zenoh thread's time. ``tick()`` (about
once a second) adds a ``status`` message: each vehicle alive / GONE / starting and why, or that
no daemon was found at all.

Messages (one JSON object per SSE ``data:`` line):
    {"type": "snapshot", "vehicles": {name: {...}}, "events": [...], "tracks": {name: [[lat, lon], ...]},
     "calibrations": {name: [latest payload per kind]}, ...}
    {"type": "sample", "vehicle": name, "topic": topic, "payload": {...}}
    {"type": "alive", "vehicle": name, "alive": bool}
    {"type": "status", "vehicles": {name: {"status", "status_reason", "last_rx_age_s"}},
     "no_daemon": bool, "message": str}
"""
from __future__ import annotations

import json
import queue
import threading
from collections import deque

from service.watch import WatchState, no_daemon_message
from service.zenoh_bus import KEY_PREFIX

CLIENT_QUEUE_MAX = 2000
"""Messages buffered per browser (about 20 s of one vehicle's 20 Hz attitude plus the rest)."""
TRACK_POINTS_MAX = 20_000
"""Dead-reckoned positions kept per vehicle (the geofence topic's 2 Hz: about 2.8 h)."""
EVENTS_MAX = 40
"""Events kept per vehicle for a browser that connects later (the page shows as many)."""


class Client:
    """One browser's queue of JSON lines."""

    def __init__(self, maxsize: int = CLIENT_QUEUE_MAX):
        self.queue: queue.Queue[str] = queue.Queue(maxsize)
        self.dropped = 0

    def put(self, line: str) -> None:
        while True:
            try:
                self.queue.put_nowait(line)
                return
            except queue.Full:
                try:  # drop the oldest: the newest state matters most
                    self.queue.get_nowait()
                    self.dropped += 1
                except queue.Empty:
                    pass


class Hub:
    def __init__(self, endpoints: list[str], vehicle_filter: str | None = None, clock=None):
        self.state = WatchState(vehicle_filter, **({"clock": clock} if clock else {}))
        self.endpoints = list(endpoints)
        self.lock = threading.Lock()
        self.clients: list[Client] = []
        self.tracks: dict[str, deque] = {}
        self.events: dict[str, deque] = {}
        self.calibrations: dict[str, dict[str, dict]] = {}

    # --- from Zenoh -----------------------------------------------------------------------------

    def on_sample(self, key: str, payload_text: str) -> None:
        """After ``state.on_sample`` has stored it (service.watch.subscribe calls this second)."""
        parts = key.split("/")
        if len(parts) != 3 or parts[0] != KEY_PREFIX:
            return
        _, name, topic = parts
        if self.state.filter and name != self.state.filter:
            return
        try:
            payload = json.loads(payload_text)
        except ValueError:
            return
        if not isinstance(payload, dict):
            return
        with self.lock:  # what a browser connecting later needs beyond the latest payload
            if topic == "geofence":
                lat, lon = payload.get("lat_deg"), payload.get("lon_deg")
                if isinstance(lat, (int, float)) and isinstance(lon, (int, float)):
                    track = self.tracks.setdefault(name, deque(maxlen=TRACK_POINTS_MAX))
                    if not track or track[-1] != [lat, lon]:
                        track.append([lat, lon])
            elif topic == "events":
                self.events.setdefault(name, deque(maxlen=EVENTS_MAX)).append({"vehicle": name, **payload})
            elif topic == "calibration":
                self.calibrations.setdefault(name, {})[str(payload.get("kind"))] = payload
        self._broadcast({"type": "sample", "vehicle": name, "topic": topic, "payload": payload})

    def on_liveliness(self, key: str, alive: bool) -> None:
        parts = key.split("/")
        if len(parts) != 3 or parts[0] != KEY_PREFIX or parts[2] != "alive":
            return
        if self.state.filter and parts[1] != self.state.filter:
            return
        self._broadcast({"type": "alive", "vehicle": parts[1], "alive": alive})

    # --- to browsers ----------------------------------------------------------------------------

    def status(self) -> dict:
        snap = self.state.snapshot()
        none = not snap["vehicles"]
        return {"type": "status", "no_daemon": none,
                "message": no_daemon_message(self.endpoints) if none else "",
                "vehicles": {n: {k: v[k] for k in ("status", "status_reason", "last_rx_age_s")}
                             for n, v in snap["vehicles"].items()}}

    def snapshot(self) -> dict:
        """Everything a browser that just connected needs to draw the current picture."""
        snap = self.state.snapshot()
        with self.lock:
            tracks = {n: list(t) for n, t in self.tracks.items()}
            events = sorted((e for q in self.events.values() for e in q),
                            key=lambda e: e.get("time_unix_s") or 0.0)
            calibrations = {n: list(c.values()) for n, c in self.calibrations.items()}
        return {"type": "snapshot", "endpoints": self.endpoints,
                "vehicles": {n: {"latest": v["latest"], "alive": v["alive"]}
                             for n, v in snap["vehicles"].items()},
                "events": events, "tracks": tracks, "calibrations": calibrations,
                "status": self.status()}

    def connect(self) -> Client:
        client = Client()
        client.put(json.dumps(self.snapshot(), separators=(",", ":")))
        with self.lock:
            self.clients.append(client)
        return client

    def disconnect(self, client: Client) -> None:
        with self.lock:
            if client in self.clients:
                self.clients.remove(client)

    def tick(self) -> None:
        self._broadcast(self.status())

    def _broadcast(self, msg: dict) -> None:
        line = json.dumps(msg, separators=(",", ":"))
        with self.lock:
            clients = list(self.clients)
        for c in clients:
            c.put(line)
