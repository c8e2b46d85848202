"""Reliability benches: bad bytes into the MAVLink receive path (``--fuzz``) and IMU load through
the daemon process (``--load``).

    python bench/reliability_load.py [--quick] [--json PATH] [--fuzz] [--load] [--frames N]
                                     [--load-s S] [--imu-hz HZ]

Default: both. ``--quick``: 100 k frames and a 60 s load run; otherwise 1 M frames and a 30 min
load run at 1 kHz (the issue's figures).

Fuzz (``fuzz_stream`` + ``run_fuzz``; tests/test_reliability_fuzz.py runs the same code at 100 k):
a seeded stream of MAVLink frames from the flight controller (system 1, component 1), MAVLink 1
and 2 mixed, in which frames are damaged as a link damages them: bad CRC (a flipped payload or
CRC byte), truncated, a wrong length byte, bad MAVLink 2 incompat flags, unknown message ids,
random garbage between frames, frames from another system. Each FC frame takes the next MAVLink
sequence number whether it arrives intact or not, as on a real link. The stream is fed to
``MavlinkLink.feed`` in random fragments (a serial port's chunks). The accounting:

    FC frames sent  ==  link.stats.accepted (delivered)  +  link.stats.seq_lost (lost, from the sequence)

exactly; every delivered RAW_IMU became an ImuSample or a counted stale-time drop; every
ImuSample equals the values its frame was built from (a damaged frame never leaks a value);
bad bytes show in crc_errors / framing_errors / unknown_ids; parser_errors stays 0.

Load (``run_load``): simulator + daemon as processes (bench/sitl.py), real time, RAW_IMU requested
at ``--imu-hz``; the daemon's own counters from its "stopped" log line: IMU messages its link
accepted (``imu_messages``) against the samples its Pipeline took (``imu_samples`` +
``imu_rejected``) = lost inside the daemon; lost before it (socket buffer, sender) from the MAVLink
sequence (``link_seq_lost``); the daemon's RSS at start and end and its CPU (psutil).
"""
from __future__ import annotations

import argparse
import json
import os
import re
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

os.environ["MAVLINK20"] = "1"

for _v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")   # small matrices: BLAS threads only spin on a shared machine (tests/conftest.py)
import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from pymavlink.dialects.v10 import ardupilotmega as mavlink1  # noqa: E402
from pymavlink.dialects.v20 import ardupilotmega as mavlink2  # noqa: E402

FC_SYS, FC_COMP = 1, 1
IMU_PERIOD_US = 5000

# frame kinds and their probabilities in the fuzz stream
KINDS = {
    "imu_v2": 0.30, "imu_v1": 0.10, "attitude_v2": 0.08, "pressure_v1": 0.05, "heartbeat_v2": 0.02,
    "bad_crc": 0.10, "truncated": 0.06, "wrong_length": 0.06, "bad_flags": 0.03,
    "unknown_id_v2": 0.04, "unknown_id_v1": 0.02, "garbage": 0.08, "foreign_v2": 0.06,
}
TRAILER_ZEROS = 300
INTACT_FC = ("imu_v2", "imu_v1", "attitude_v2", "pressure_v1", "heartbeat_v2")
DAMAGED_FC = ("bad_crc", "truncated", "wrong_length", "bad_flags", "unknown_id_v2", "unknown_id_v1")


def imu_raw_values(k: int) -> tuple[int, ...]:
    """The RAW_IMU integer fields (xacc..zmag) of frame k: a deterministic function of k."""
    return (k % 97 - 48, (k * 7) % 101 - 50, -1000 + k % 13, (k * 3) % 211 - 105, (k * 5) % 199 - 99,
            (k * 11) % 223 - 111, 200 + k % 7, -50 + k % 5, 400 + k % 3)


@dataclass
class FuzzStream:
    data: bytes
    frames: int
    kinds: dict[str, int]
    fc_frames: int
    """Frames from the FC (each took a sequence number), intact or damaged."""
    imu_values: dict[int, tuple[int, ...]] = field(repr=False)
    """time_usec -> RAW_IMU fields of every RAW_IMU frame built (intact or damaged)."""
    bounds: list = field(default_factory=list, repr=False)
    """Byte offsets of the frame boundaries (0, end of frame 1, ..., len(data)): datagrams."""


class _Packer:
    """Packs frames from the FC with one shared MAVLink sequence counter for v1 and v2."""

    def __init__(self):
        self.v2 = mavlink2.MAVLink(None, srcSystem=FC_SYS, srcComponent=FC_COMP)
        self.v1 = mavlink1.MAVLink(None, srcSystem=FC_SYS, srcComponent=FC_COMP)
        self.other = mavlink2.MAVLink(None, srcSystem=7, srcComponent=1)
        self.seq = 0

    def fc(self, msg, v1: bool = False) -> bytes:
        mav = self.v1 if v1 else self.v2
        mav.seq = self.seq
        self.seq = (self.seq + 1) % 256
        return bytes(msg.pack(mav))

    def unknown(self, v1: bool, rng: np.random.Generator) -> bytes:
        """A well-framed message with an id no dialect knows (v2: 3-byte id; v1: 1-byte id of an
        unassigned number), from the FC, with its sequence number."""
        payload = rng.integers(0, 256, int(rng.integers(1, 40)), dtype=np.uint8).tobytes()
        seq = self.seq
        self.seq = (self.seq + 1) % 256
        if v1:
            msgid = 255  # unassigned in common/ardupilotmega
            hdr = bytes([0xFE, len(payload), seq, FC_SYS, FC_COMP, msgid])
        else:
            msgid = 16_000_000 + int(rng.integers(0, 700_000))
            hdr = bytes([0xFD, len(payload), 0, 0, seq, FC_SYS, FC_COMP,
                         msgid & 0xFF, (msgid >> 8) & 0xFF, msgid >> 16])
        from pymavlink.generator.mavcrc import x25crc
        crc = x25crc(hdr[1:] + payload)
        crc.accumulate(bytes([77]))  # some CRC_EXTRA: the receiver cannot know it
        return hdr + payload + crc.crc.to_bytes(2, "little")


def fuzz_stream(n_frames: int, seed: int = 0) -> FuzzStream:
    """``n_frames`` frames, seeded; the first and last are intact FC heartbeats (the link learns
    the autopilot from the first; the last closes the sequence accounting)."""
    rng = np.random.default_rng(seed)
    names = list(KINDS)
    p = np.array([KINDS[k] for k in names])
    choice = rng.choice(len(names), size=n_frames, p=p / p.sum())
    pk = _Packer()
    out = []
    kinds = {k: 0 for k in names}
    imu_values: dict[int, tuple[int, ...]] = {}
    fc_frames = 0
    hb = mavlink2.MAVLink_heartbeat_message(1, 3, 0, 0, 4, 3)  # fixed wing, ArduPilot, active
    for k in range(n_frames):
        kind = "heartbeat_v2" if k in (0, n_frames - 1) else names[choice[k]]
        kinds[kind] += 1
        t_us = 1_000_000 + IMU_PERIOD_US * k
        if kind in ("imu_v2", "imu_v1") or kind in ("bad_crc", "truncated", "wrong_length", "bad_flags"):
            vals = imu_raw_values(k)
            imu_values[t_us] = vals
            v1 = kind == "imu_v1" or (kind != "imu_v2" and kind != "bad_flags" and k % 3 == 0)
            msg = (mavlink1.MAVLink_raw_imu_message(t_us, *vals) if v1
                   else mavlink2.MAVLink_raw_imu_message(t_us, *vals, 0, 0))
            frame = bytearray(pk.fc(msg, v1=v1))
            fc_frames += 1
            hlen = 6 if v1 else 10
            if kind == "bad_crc":
                pos = int(rng.integers(hlen, len(frame)))  # payload or CRC
                frame[pos] ^= int(rng.integers(1, 256))
            elif kind == "truncated":
                frame = frame[:int(rng.integers(1, len(frame)))]
            elif kind == "wrong_length":
                new = int(rng.integers(0, 256))
                frame[1] = new if new != frame[1] else (new + 1) % 256
            elif kind == "bad_flags":
                frame[2] |= 1 << int(rng.integers(1, 8))  # an incompat flag no one defines
            out.append(bytes(frame))
        elif kind == "attitude_v2":
            out.append(pk.fc(mavlink2.MAVLink_attitude_message(t_us // 1000, 0.1, -0.2, 0.3, 0.01, 0.02, 0.03)))
            fc_frames += 1
        elif kind == "pressure_v1":
            out.append(pk.fc(mavlink1.MAVLink_scaled_pressure_message(t_us // 1000, 1000.0 + k % 10, 0.5, 2000),
                             v1=True))
            fc_frames += 1
        elif kind == "heartbeat_v2":
            out.append(pk.fc(hb))
            fc_frames += 1
        elif kind in ("unknown_id_v2", "unknown_id_v1"):
            out.append(pk.unknown(kind == "unknown_id_v1", rng))
            fc_frames += 1
        elif kind == "garbage":
            out.append(rng.integers(0, 256, int(rng.integers(1, 64)), dtype=np.uint8).tobytes())
        elif kind == "foreign_v2":
            out.append(bytes(mavlink2.MAVLink_attitude_message(k, 0, 0, 0, 0, 0, 0).pack(pk.other)))
    # the last heartbeat must arrive for the sequence accounting to close: a damaged frame just
    # before it may claim up to 280 bytes, which idle-line zeros satisfy (counted as bad data)
    out.insert(len(out) - 1, bytes(TRAILER_ZEROS))
    bounds = np.concatenate(([0], np.cumsum([len(b) for b in out]))).tolist()
    return FuzzStream(b"".join(out), n_frames, kinds, fc_frames, imu_values, bounds)


def run_fuzz(stream: FuzzStream, seed: int = 0, max_chunk: int = 512, datagrams: bool = False,
             reset_per_datagram: bool = False, datagram_semantics: bool | None = None) -> dict:
    """Feed the stream to a MavlinkLink in random fragments (``datagrams``: one frame per feed,
    as UDP delivers) and check the accounting.

    ``datagram_semantics``: whether the link treats each feed as one UDP datagram (its parser
    reset at a datagram that starts with a magic byte while a partial frame is held, and its
    learning of a sender that splits frames); None = ``datagrams`` (what the link does on UDP).
    ``False`` with ``datagrams`` measures the link as it was before (a byte stream);
    ``reset_per_datagram``: an unconditional reset before every feed (the upper bound).

    Returns the figures (counts, time) and ``problems``: a list of broken invariants (empty = pass)."""
    from mavlink_io.link import LinkConfig, MavlinkLink
    from mavlink_io.samples import ImuSample
    from mavlink_io.transport import NullTransport
    from mavlink_io.decode import MG_TO_M_S2, MRAD_TO_RAD

    clock = [0.0]
    link = MavlinkLink(LinkConfig(url="udpin:127.0.0.1:0"), clock=lambda: clock[0], transport=NullTransport(None))
    rng = np.random.default_rng(seed + 1)
    data = stream.data
    cuts = np.cumsum(rng.integers(1, max_chunk + 1, size=len(data) // max(1, max_chunk // 2) + 2))
    cuts = cuts[cuts < len(data)]
    bounds = stream.bounds if datagrams else [0, *cuts.tolist(), len(data)]
    semantics = datagrams if datagram_semantics is None else datagram_semantics
    n_imu = 0
    bad_values = 0
    worst_feed_s = worst_feed_cpu_s = 0.0
    t0, cpu0 = time.perf_counter(), time.thread_time()
    for i in range(len(bounds) - 1):
        clock[0] += 0.001
        ts, cs = time.perf_counter(), time.thread_time()
        if reset_per_datagram:
            link._reset_parser()  # noqa: SLF001 - the measurement of a possible fix
        items = link.feed(data[bounds[i]:bounds[i + 1]], clock[0], datagram=semantics)
        worst_feed_s = max(worst_feed_s, time.perf_counter() - ts)
        worst_feed_cpu_s = max(worst_feed_cpu_s, time.thread_time() - cs)
        for it in items:
            if isinstance(it, ImuSample):
                n_imu += 1
                vals = stream.imu_values.get(round(it.time_fc_s * 1e6))
                if vals is None or not (np.array_equal(it.accel_m_s2, np.array(vals[0:3], float) * MG_TO_M_S2)
                                        and np.array_equal(it.gyro_rad_s, np.array(vals[3:6], float) * MRAD_TO_RAD)):
                    bad_values += 1
    elapsed = time.perf_counter() - t0
    cpu_s = time.thread_time() - cpu0  # this thread's CPU: what a hang costs, whatever the machine's load
    s = link.stats
    problems = []
    if s.accepted + s.seq_lost != stream.fc_frames:
        problems.append(f"FC frames {stream.fc_frames} != accepted {s.accepted} + seq_lost {s.seq_lost}")
    if s.seq_duplicates or s.seq_reordered:
        problems.append(f"sequence duplicates {s.seq_duplicates} / reordered {s.seq_reordered} on a stream with none")
    raw_imu = s.messages_by_type.get("RAW_IMU", 0)
    if raw_imu != n_imu + s.stale_time_drops:
        problems.append(f"RAW_IMU accepted {raw_imu} != ImuSamples {n_imu} + stale drops {s.stale_time_drops}")
    if bad_values:
        problems.append(f"{bad_values} ImuSamples whose values differ from the frame they came from")
    if s.parser_errors:
        problems.append(f"parser_errors {s.parser_errors}")
    if s.bytes_received != len(data):
        problems.append(f"bytes_received {s.bytes_received} != {len(data)} fed")
    intact = sum(stream.kinds[k] for k in INTACT_FC)
    damaged = sum(stream.kinds[k] for k in DAMAGED_FC) + stream.kinds["garbage"]
    if s.accepted > intact:
        problems.append(f"accepted {s.accepted} > intact FC frames {intact} (a damaged frame got through)")
    if s.foreign_messages > stream.kinds["foreign_v2"]:
        problems.append(f"foreign {s.foreign_messages} > foreign frames sent {stream.kinds['foreign_v2']}")
    bad_counted = s.crc_errors + s.framing_errors + s.unknown_ids
    if bad_counted == 0 and damaged:
        problems.append("no bad frame counted")
    return {"frames": stream.frames, "bytes": len(data), "fc_frames": stream.fc_frames,
            "intact_fc_frames": intact, "damaged_frames": damaged, "kinds": stream.kinds,
            "accepted": s.accepted, "seq_lost": s.seq_lost, "crc_errors": s.crc_errors,
            "framing_errors": s.framing_errors, "unknown_ids": s.unknown_ids,
            "foreign_messages": s.foreign_messages, "imu_samples": n_imu,
            "stale_time_drops": s.stale_time_drops, "parser_errors": s.parser_errors,
            "intact_lost_to_neighbours": intact - s.accepted,
            "datagram_resets": s.datagram_resets, "udp_split_frames_seen": s.udp_split_frames_seen,
            "elapsed_s": elapsed, "frames_per_s": stream.frames / elapsed, "worst_feed_ms": 1e3 * worst_feed_s,
            "cpu_s": cpu_s, "worst_feed_cpu_ms": 1e3 * worst_feed_cpu_s,
            "problems": problems}


# --- load -----------------------------------------------------------------------------------

STOPPED_KEYS = ("imu_samples", "imu_rejected", "imu_messages", "link_accepted", "link_seq_lost", "link_bad_data",
                "link_stale_drops", "link_losses", "fc_reboots")


def daemon_stopped_counts(log_text: str) -> dict | None:
    """The counters of the daemon's "stopped" log line (service/daemon.py close()), or None."""
    line = next((ln for ln in log_text.splitlines() if "msg=stopped" in ln), None)
    if line is None:
        return None
    out = {}
    for k in STOPPED_KEYS:
        m = re.search(rf"\b{k}=(\d+)", line)
        if m:
            out[k] = int(m.group(1))
    return out


DRAIN_WAIT_S = 120.0
"""At most this long for the daemon to read its socket's backlog once the simulator stopped."""


def run_load(duration_s: float, imu_hz: float = 1000.0, seed: int = 5) -> dict:
    """Simulator + daemon (as processes, real time) with RAW_IMU at ``imu_hz`` for ``duration_s``
    wall seconds. In vs processed inside the daemon: the IMU messages its link accepted
    (``imu_messages``) against the samples its Pipeline took (``imu_samples`` + ``imu_rejected``)
    plus the link's stale-time drops; lost before the daemon (socket buffer, the sender):
    ``link_seq_lost``. RSS and CPU of the daemon process by psutil."""
    import psutil

    sys.path.insert(0, str(ROOT / "bench"))
    from sitl import Sitl

    sim_s = duration_s + 30.0
    with Sitl(scenario="inclined_rail", speed=1.0, seed=seed,
              config_overrides={"mavlink": {"imu_rate_hz": float(imu_hz)}},
              sim_args=["--duration", str(sim_s)]) as s:
        proc = psutil.Process(s.daemon.pid)
        s.wait_for(lambda: "flight controller link up" in s.log("daemon"), 60)
        time.sleep(3.0)  # the streams are requested and running
        rss_start = proc.memory_info().rss
        cpu0 = proc.cpu_times()
        t0 = time.monotonic()
        rss = [(0.0, rss_start)]
        while time.monotonic() - t0 < duration_s - 3.0 and s.sim.poll() is None:
            time.sleep(min(10.0, max(1.0, duration_s / 20)))
            rss.append((time.monotonic() - t0, proc.memory_info().rss))
        cpu1 = proc.cpu_times()
        wall = time.monotonic() - t0
        rss_end = proc.memory_info().rss
        # the simulator first, then let the daemon read what is still queued for it (it says
        # link_lost once it has read everything and heard nothing for its link timeout): stopping
        # both at once lost a behind daemon's socket backlog uncounted (22 % at load 11-15)
        losses_before = s.log("daemon").count("event=link_lost")
        s.sim.terminate()
        s.sim.wait(30)
        t_drain = time.monotonic() + DRAIN_WAIT_S
        while time.monotonic() < t_drain and s.daemon.poll() is None \
                and s.log("daemon").count("event=link_lost") <= losses_before:
            time.sleep(0.2)
        s.stop()
        daemon_log = s.log("daemon")
    c = daemon_stopped_counts(daemon_log) or {}
    processed = c.get("imu_samples", 0) + c.get("imu_rejected", 0)
    in_daemon = c.get("imu_messages", 0) - c.get("link_stale_drops", 0)
    rate = c.get("imu_messages", 0) / (duration_s + 3.0)
    half = [r for t, r in rss if t >= wall / 2]
    return {"imu_rate_requested_hz": imu_hz, "duration_s": duration_s, **c,
            "imu_processed": processed, "imu_lost_inside_daemon": in_daemon - processed,
            "imu_rate_received_hz_approx": rate,
            "daemon_cpu_percent": 100.0 * ((cpu1.user - cpu0.user) + (cpu1.system - cpu0.system)) / wall,
            "rss_start_mb": rss_start / 2**20, "rss_end_mb": rss_end / 2**20,
            "rss_max_mb": max(r for _t, r in rss) / 2**20,
            "rss_second_half_growth_mb": (half[-1] - half[0]) / 2**20 if len(half) > 1 else 0.0,
            "workdir": str(s.workdir)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--json", default=str(ROOT / "bench" / "results" / "reliability_load.json"))
    ap.add_argument("--fuzz", action="store_true", help="only the fuzz part")
    ap.add_argument("--load", action="store_true", help="only the load part")
    ap.add_argument("--frames", type=int, default=None)
    ap.add_argument("--load-s", type=float, default=None)
    ap.add_argument("--imu-hz", type=float, default=1000.0)
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args(argv)
    both = not a.fuzz and not a.load
    results: dict = {}
    if a.fuzz or both:
        n = a.frames or (100_000 if a.quick else 1_000_000)
        t0 = time.perf_counter()
        stream = fuzz_stream(n, a.seed)
        gen_s = time.perf_counter() - t0
        r = run_fuzz(stream, a.seed)
        r["generate_s"] = gen_s
        results["fuzz"] = r
        print(f"fuzz: {r['frames']} frames ({r['bytes']} bytes, {r['damaged_frames']} damaged) in "
              f"{r['elapsed_s']:.1f} s ({r['frames_per_s']:.0f} frames/s), worst feed {r['worst_feed_ms']:.1f} ms")
        print(f"  FC frames {r['fc_frames']} = accepted {r['accepted']} + seq_lost {r['seq_lost']}; "
              f"crc {r['crc_errors']} framing {r['framing_errors']} unknown {r['unknown_ids']} "
              f"foreign {r['foreign_messages']}; intact frames lost to a damaged neighbour "
              f"{r['intact_lost_to_neighbours']}")
        print("  problems: " + ("none" if not r["problems"] else "; ".join(r["problems"])))
        for name, label, kw in (
                ("datagrams_as_stream", "one frame per datagram, parsed as a byte stream (the link before)",
                 {"datagrams": True, "datagram_semantics": False}),
                ("datagrams", "one frame per datagram, the link as it is (reset at a magic byte)",
                 {"datagrams": True}),
                ("datagrams_reset", "one frame per datagram, unconditional reset (upper bound)",
                 {"datagrams": True, "reset_per_datagram": True}),
                ("split_as_stream", "random fragments as datagrams, parsed as a byte stream (the link before)",
                 {"datagram_semantics": False}),
                ("split", "random fragments as datagrams (serial-to-UDP bridge), the link as it is",
                 {"datagram_semantics": True})):
            d = run_fuzz(stream, a.seed, **kw)
            results["fuzz_" + name] = d
            print(f"  {label}: accepted {d['accepted']} of {d['intact_fc_frames']} intact FC frames "
                  f"({d['intact_lost_to_neighbours']} lost), datagram resets {d['datagram_resets']}, split frames "
                  f"seen {d['udp_split_frames_seen']}; problems: "
                  + ("none" if not d["problems"] else "; ".join(d["problems"])))
    if a.load or both:
        dur = a.load_s or (60.0 if a.quick else 1800.0)
        r = run_load(dur, a.imu_hz)
        results["load"] = r
        print(f"load: {r['imu_rate_requested_hz']:.0f} Hz RAW_IMU requested, {dur:.0f} s: link accepted "
              f"{r.get('imu_messages')} IMU messages (~{r['imu_rate_received_hz_approx']:.0f} Hz), lost before "
              f"the daemon (sequence) {r.get('link_seq_lost')}, Pipeline processed {r['imu_processed']} "
              f"(rejected {r.get('imu_rejected')}), lost inside the daemon {r['imu_lost_inside_daemon']}; "
              f"CPU {r['daemon_cpu_percent']:.0f} % of a core; RSS {r['rss_start_mb']:.1f} -> "
              f"{r['rss_end_mb']:.1f} MB (max {r['rss_max_mb']:.1f}, second half {r['rss_second_half_growth_mb']:+.1f})")
    Path(a.json).parent.mkdir(parents=True, exist_ok=True)
    Path(a.json).write_text(json.dumps(results, indent=1, default=str))
    ok = all(not v.get("problems") for v in results.values())
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
