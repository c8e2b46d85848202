"""The link's settings and what it reports: LinkConfig (validated on construction), LinkEvent, the
event kinds, the default stream rates, and MAVLink message name -> id.

Shared by the modules of the link (session, security, stream_rates, sample_decoder, link); imports
nothing of them.
"""
from __future__ import annotations

import os

os.environ["MAVLINK20"] = "1"  # before the first pymavlink import (mavutil reads it at import)

from dataclasses import dataclass, field

from pymavlink.dialects.v20 import ardupilotmega as mavlink2

from mavlink_io.signing import TIMESTAMP_MAX, check_key
from mavlink_io.transport import UDP_RCVBUF_BYTES_DEFAULT
from mavlink_io.url import parse_url

LINK_EVENT_KINDS = ("autopilot_detected", "rates_requested", "rates_acked", "rates_limited", "fc_reboot",
                    "time_gap", "time_wrap", "link_lost", "link_restored", "reconnect", "transport_error",
                    "signature_rejected", "unsigned_command_rejected", "udp_split_frames", "params_read",
                    "input_backlog")
REQUIRE_SIGNED = ("commands", "all", "none")

DEFAULT_STREAM_RATES_HZ = {"RAW_IMU": 200.0, "SCALED_PRESSURE": 50.0, "ATTITUDE": 50.0,
                           "EKF_STATUS_REPORT": 2.0, "SYS_STATUS": 2.0, "HIGHRES_IMU": 200.0,
                           "EXTENDED_SYS_STATE": 2.0}
IMU_SOURCES = ("RAW_IMU", "HIGHRES_IMU", "SCALED_IMU")


@dataclass(frozen=True, slots=True)
class LinkEvent:
    """Something the daemon should know about the link or the FC clock.

    kind: one of LINK_EVENT_KINDS; detail: human-readable, names the values; time_rx_s: local
    monotonic time (the link's clock)."""
    kind: str
    detail: str
    time_rx_s: float


@dataclass(frozen=True)
class LinkConfig:
    """Link settings; validated on construction (ValueError naming the field)."""
    url: str
    component_id: int = 191
    """Our MAVLink component id (191 = MAV_COMP_ID_ONBOARD_COMPUTER)."""
    system_id: int | None = None
    """The vehicle's system id; None = learn it from the autopilot's HEARTBEAT."""
    heartbeat_hz: float = 1.0
    link_timeout_s: float = 2.0
    """No message from the autopilot for this long -> link_lost."""
    imu_gap_s: float = 0.5
    """IMU samples further apart than this (FC time) -> time_gap event."""
    stream_rates_hz: dict = field(default_factory=lambda: dict(DEFAULT_STREAM_RATES_HZ))
    """Message name -> requested rate, Hz. Names the autopilot does not send are skipped (PX4: RAW_IMU,
    EKF_STATUS_REPORT; on PX4, EKF_STATUS_REPORT's rate is used for ESTIMATOR_STATUS; ArduPilot:
    ESTIMATOR_STATUS, and HIGHRES_IMU when RAW_IMU is requested)."""
    autopilot_component_id: int | None = None
    """The autopilot's component id; None = learn it from its HEARTBEAT (normally 1)."""
    imu_source: str = "auto"
    """"auto" (ArduPilot: RAW_IMU > HIGHRES_IMU > SCALED_IMU; others: HIGHRES_IMU first) or one name."""
    imu_id: int = 0
    """Which IMU instance (RAW_IMU/HIGHRES_IMU ``id``) to use."""
    reboot_jump_s: float = 1.0
    """FC time going back by more than this is a reboot; less is a reordered packet (dropped)."""
    ack_timeout_s: float = 0.5
    request_tries: int = 3
    stream_recheck_s: float = 5.0
    """A requested stream silent for link_timeout_s is re-requested, at most this often; 0 = never."""
    reconnect_backoff_s: float = 0.5
    reconnect_backoff_max_s: float = 5.0
    rate_window_s: float = 2.0
    rate_floor_hz: float | None = 1.0
    """A refused stream rate is asked again at half the rate while that is >= this (Hz); None = a
    refusal is final."""
    signing_key: bytes | None = field(default=None, repr=False, compare=False)
    """MAVLink 2 signing secret key, exactly 32 bytes; None = no signing (everything accepted as
    unsigned, nothing signed). Never shown in repr/str or in any error message."""
    sign_outgoing: bool = True
    """With a key: sign what we send."""
    require_signed: str = "commands"
    """With a key: which unsigned frames are dropped. "commands": COMMAND_LONG/COMMAND_INT addressed
    to us (our system or 0, our component or 0); "all": every unsigned frame (MAVLink 1 included);
    "none": none. A signed frame that fails verification is always dropped."""
    signing_link_id: int = 0
    """Our link id in the signature block (0..255)."""
    signing_timestamp_floor: int = 0
    """Our outgoing signing timestamps start above max(this, the wall clock), in 10 us units since
    2015-01-01 UTC (persist ``link.signing_timestamp`` and pass it back here after a restart)."""
    udp_rcvbuf_bytes: int = UDP_RCVBUF_BYTES_DEFAULT
    """UDP receive buffer asked for (SO_RCVBUF; the kernel caps it at net.core.rmem_max)."""
    imu_batch: bool = False
    """The batch path (mavlink_io.imu_batch): the RAW_IMU samples of a read come out of poll() as
    one ImuBatch per run of consecutive samples instead of one ImuSample each (the daemon's
    choice; replay and tools keep ImuSample). Used only without a signing key (signed and unsigned
    frames then need pymavlink and the security checks) and while no subscriber asked for every
    message."""

    def __post_init__(self) -> None:
        _check_int("udp_rcvbuf_bytes", self.udp_rcvbuf_bytes, 4096, 2**31 - 1)
        parse_url(self.url)  # ValueError naming the URL
        _check_int("component_id", self.component_id, 1, 255)
        if self.system_id is not None:
            _check_int("system_id", self.system_id, 1, 255)
        if self.autopilot_component_id is not None:
            _check_int("autopilot_component_id", self.autopilot_component_id, 1, 255)
        _check_int("imu_id", self.imu_id, 0, 255)
        _check_int("request_tries", self.request_tries, 1, 20)
        for name, lo, hi in (("heartbeat_hz", 0.0, 50.0), ("link_timeout_s", 0.0, 3600.0),
                             ("imu_gap_s", 0.0, 3600.0), ("reboot_jump_s", 0.0, 3600.0),
                             ("ack_timeout_s", 0.0, 60.0), ("reconnect_backoff_s", 0.0, 60.0),
                             ("reconnect_backoff_max_s", 0.0, 3600.0), ("rate_window_s", 0.0, 60.0)):
            v = getattr(self, name)
            if not isinstance(v, (int, float)) or not lo < v <= hi:
                raise ValueError(f"LinkConfig.{name} must be in ({lo:g}, {hi:g}], got {v!r}")
        if self.rate_floor_hz is not None and (not isinstance(self.rate_floor_hz, (int, float))
                                               or not 0 < self.rate_floor_hz <= 1000):
            raise ValueError(f"LinkConfig.rate_floor_hz must be None or in (0, 1000] Hz, got {self.rate_floor_hz!r}")
        if not isinstance(self.stream_recheck_s, (int, float)) or not 0 <= self.stream_recheck_s <= 3600:
            raise ValueError(f"LinkConfig.stream_recheck_s must be in [0, 3600], got {self.stream_recheck_s!r}")
        if self.reconnect_backoff_max_s < self.reconnect_backoff_s:
            raise ValueError("LinkConfig.reconnect_backoff_max_s must be >= reconnect_backoff_s, got "
                             f"{self.reconnect_backoff_max_s} < {self.reconnect_backoff_s}")
        if self.imu_source != "auto" and self.imu_source not in IMU_SOURCES:
            raise ValueError(f"LinkConfig.imu_source must be 'auto' or one of {', '.join(IMU_SOURCES)}, "
                             f"got {self.imu_source!r}")
        if self.signing_key is not None:
            check_key(self.signing_key, "LinkConfig.signing_key")
        if not isinstance(self.imu_batch, bool):
            raise ValueError(f"LinkConfig.imu_batch must be true or false, got {self.imu_batch!r}")
        if not isinstance(self.sign_outgoing, bool):
            raise ValueError(f"LinkConfig.sign_outgoing must be true or false, got {self.sign_outgoing!r}")
        if self.require_signed not in REQUIRE_SIGNED:
            raise ValueError(f"LinkConfig.require_signed must be one of {', '.join(REQUIRE_SIGNED)}, "
                             f"got {self.require_signed!r}")
        _check_int("signing_link_id", self.signing_link_id, 0, 255)
        _check_int("signing_timestamp_floor", self.signing_timestamp_floor, 0, TIMESTAMP_MAX - 1)
        if not isinstance(self.stream_rates_hz, dict):
            raise ValueError(f"LinkConfig.stream_rates_hz must be a dict name -> Hz, got {type(self.stream_rates_hz).__name__}")
        for name, rate in self.stream_rates_hz.items():
            if message_id(name) is None:
                raise ValueError(f"LinkConfig.stream_rates_hz: unknown MAVLink message {name!r}")
            if not isinstance(rate, (int, float)) or not 0 < rate <= 1000:
                raise ValueError(f"LinkConfig.stream_rates_hz[{name!r}] must be in (0, 1000] Hz, got {rate!r}")


def _check_int(name: str, v, lo: int, hi: int) -> None:
    if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
        raise ValueError(f"LinkConfig.{name} must be an integer in [{lo}, {hi}], got {v!r}")


def message_id(name: str) -> int | None:
    """MAVLink message name -> id in the ardupilotmega dialect (None if unknown)."""
    return getattr(mavlink2, f"MAVLINK_MSG_ID_{name}", None) if isinstance(name, str) else None


@dataclass(slots=True)
class FcPeer:
    """The autopilot the link talks to: its ids (None until learned) and family
    ("ardupilot" | "px4" | "other" | None)."""
    system: int | None = None
    component: int | None = None
    autopilot: str | None = None

    @property
    def known(self) -> bool:
        return self.system is not None and self.component is not None
