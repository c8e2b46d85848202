"""The daemon's guard on the heading feed: may ODOMETRY go to the FC, and is the FC's yaw our own?

Decisions from mavlink_io.fc_yaw_feed (the FC's parameters), kept up to date as PARAM_VALUEs arrive
(a ground station changing a parameter is seen too), plus the FC's own words: a STATUSTEXT
"EKFn IMUm is using external nav data" after we sent ODOMETRY means an estimator took our
placeholder position. That stops ODOMETRY for the rest of the run (latched: a position already fused
cannot be unfused) with an error that names the parameter.

Once the FC's yaw is known to come from us, the pipeline is told to exclude it everywhere
(Pipeline.exclude_fc_yaw): heading source, method B's reference yaw and KF1 learning reference,
the FC-yaw consider term. That is never undone during the run.

State only; the daemon sends and logs what the methods return: (kind, severity, detail) events.
"""
from __future__ import annotations

import re

from mavlink_io.fc_yaw_feed import FcYawFeedCheck, check_fc_yaw_feed, params_for

EXTNAV_IN_USE = re.compile(r"^(EKF[23]) IMU\d+ is using external nav data")


class FcYawGuard:
    def __init__(self):
        self.autopilot: str | None = None
        self.check: FcYawFeedCheck | None = None
        self.placeholder_fused: str | None = None
        """The FC's STATUSTEXT that showed an estimator fusing our placeholder (latched)."""
        self.exclude_reason: str | None = None
        """Why the FC's yaw is not a reference (set once, never cleared)."""

    @property
    def odometry_allowed(self) -> bool:
        return (self.placeholder_fused is None and self.check is not None
                and self.check.placeholder_safe is True)

    def start(self, autopilot: str | None) -> tuple[tuple[str, ...], list]:
        """The autopilot is known (or rebooted): the parameters to read, and the events."""
        self.autopilot = autopilot
        names = params_for(autopilot)
        self.check = None
        if not names:
            return names, self._update({}, set())
        return names, [("fc_yaw_feed", "info", f"reading {len(names)} FC parameters before any ODOMETRY "
                                                "(is the placeholder position safe, is the FC's yaw ours)")]

    def on_params(self, params: dict, missing: set) -> list:
        """The watched parameters so far (link.fc_params) and the unanswered ones."""
        return self._update(params, missing)

    def _update(self, params: dict, missing: set) -> list:
        new = check_fc_yaw_feed(self.autopilot, params, missing)
        old, self.check = self.check, new
        events = []
        if new.placeholder_safe is not None and (old is None or (old.placeholder_safe, old.reason)
                                                 != (new.placeholder_safe, new.reason)):
            events.append(("fc_yaw_feed", "info" if new.placeholder_safe else "error",
                           ("ODOMETRY allowed: " if new.placeholder_safe else "") + new.reason))
        if new.fc_yaw_from_us and self.exclude_reason is None:
            self.exclude_reason = f"the FC's yaw comes from our ODOMETRY ({new.reason})"
            events.append(("fc_yaw_loop", "warning", self.exclude_reason + ": not used as a reference"))
        return events

    def configured_exclusion(self) -> None:
        """[heading] use_fc_yaw = false: the exclusion is the operator's."""
        if self.exclude_reason is None:
            self.exclude_reason = "configured ([heading] use_fc_yaw = false)"

    def on_statustext(self, text: str, odometry_sent: bool) -> list:
        m = EXTNAV_IN_USE.match(text)
        if m is None or not odometry_sent or self.placeholder_fused is not None:
            return []
        self.placeholder_fused = text
        fix = ("set EK2_ENABLE 0 (AHRS_EKF_TYPE 3)" if m.group(1) == "EKF2"
               else "set every EK3_SRCn_POSXY/VELXY/POSZ/VELZ to a source other than 6")
        return [("placeholder_fused", "error", f"the FC said \"{text}\" after our ODOMETRY: its estimator took our "
                                               f"placeholder position; ODOMETRY stopped for this run: {fix}")]

    def flags(self) -> dict:
        """For the health topic."""
        out = {"odometry": ("stopped: " + self.placeholder_fused) if self.placeholder_fused else
               ("allowed" if self.odometry_allowed else "not sent: " + (self.check.reason if self.check
                                                                      else "autopilot not known yet"))}
        out["fc_yaw"] = ("not a reference: " + self.exclude_reason) if self.exclude_reason else (
            "independent" if self.check is not None and self.check.fc_yaw_from_us is False else "origin unknown")
        return out
