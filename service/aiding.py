"""One aiding record per heading source: what it offered, how it compared, fused or why not.

The pattern of PX4 EKF2's ``estimator_aid_source`` messages, applied to azimuthd's heading
arbitration (service/heading_arbitration.py): each source (method A ``azimuth``, method B
``synthetic_ahrs``, method C ``heading_filter``, the FC's own yaw ``fc``) offers an observation of
the heading; the arbitration compares it with its reference (the previous fused heading
propagated to now) and fuses it or says why not. Method D (``deviation``) offers no heading: it
corrects C's magnetometer, so its record says whether that correction is applied.

Arbitration-level fields (the gate that decides ``fused``; docstring steps 2-3 there):
    innovation_rad            = wrap_pi(observation - reference)
    innovation_variance_rad2  = observation_sigma^2 + reference variance
    test_ratio                = innovation^2 / innovation_variance / gate_chi2   (> 1: gated out)
Source-level fields (``source_*``): the source's OWN last measurement against its own filter,
where it computes one (method C: the magnetometer heading against its heading filter,
estimators/polar_heading HeadingDiag; its gate also rejects at a ratio > 1). NaN where the source
computes none (A, B, the FC, D): nothing is made up. C's two differ in one way, as its filter
does: its gate asks whether ONE measurement is plausible, nu^2 / (P + R_single) / gate_chi2, while
the variance it reports is the fusion's S = P + R, R inflated for the correlated error.

``why_not`` is a stable code (below, ``WHY_NOT``; "" when fused); ``detail`` is the one line a
person reads (numbers included). Pure: no I/O, no clock. Radians inside; ``payload`` and
``csv_row`` convert to degrees at the edge.
"""
from __future__ import annotations

import math
from typing import NamedTuple

SOURCES = ("azimuth", "synthetic_ahrs", "heading_filter", "fc", "deviation")
"""Every source that reports a record, in the order of the CSV columns."""

WHY_NOT = {
    "": "fused",
    "no_estimate": "the source has no heading (yet): waiting, not initialised, no input",
    "superseded": "a magnetometer source is not offered while method A has a solution that agrees with it and is as "
                  "certain (A's sigma widened by its disagreement)",
    "excluded": "switched off by configuration, or the FC's yaw is excluded",
    "no_reference": "the reference the source is built on is lost (no trusted FC, no air data)",
    "no_propagation": "the source's inputs arrive too seldom for it to propagate (method B: most of its last 5 s of "
                      "IMU intervals longer than it integrates)",
    "not_valid": "the source says its reading is not valid",
    "inconsistent": "the source's own measurements keep failing its own gate (method A: it keeps disagreeing with the sources it supersedes)",
    "non_finite": "heading, sigma or time not finite",
    "sigma_out_of_range": "sigma not in (0, max_sigma]",
    "stale": "older than the arbitration's max_age_s",
    "gated_out": "rejected by the arbitration gate (test_ratio > 1)",
    "correlated": "shares an error source with a better fused source (covariance intersection)",
    "not_applied": "method D: its correction is not applied to C's magnetometer",
}
"""Stable ``why_not`` codes and what each means (docs/OUTPUTS.md and docs/REPLAY.md list them)."""


class _AidingFields(NamedTuple):
    source: str
    time_s: float
    """FC time of the arbitration step that wrote the record (s)."""
    why_not: str = "no_estimate"
    """A ``WHY_NOT`` code: "" when fused."""
    detail: str = ""
    """One line for a person (why not, with its numbers); "" when fused."""
    candidate: bool = False
    """Offered, valid, consistent, finite, fresh and with a sigma in range."""
    fused: bool = False
    time_last_fused_s: float = math.nan
    """FC time of the last step it was fused (NaN: never in this run)."""
    observation_rad: float = math.nan
    """The heading offered (true, [0, 2pi)); NaN when none."""
    observation_sigma_rad: float = math.nan
    innovation_rad: float = math.nan
    innovation_variance_rad2: float = math.nan
    test_ratio: float = math.nan
    source_innovation_rad: float = math.nan
    source_innovation_variance_rad2: float = math.nan
    source_test_ratio: float = math.nan


class AidingRecord(_AidingFields):
    """One source's aiding record (fields above). A NamedTuple, not a dataclass: the Pipeline
    writes five at every filter step, and a frozen dataclass costs ~5x more to build."""
    __slots__ = ()

    def __new__(cls, *args, **kwargs):
        rec = super().__new__(cls, *args, **kwargs)
        if rec.why_not not in WHY_NOT:
            raise ValueError(f"why_not must be one of {sorted(WHY_NOT)}, got {rec.why_not!r}")
        if rec.fused != (rec.why_not == ""):
            raise ValueError(f"{rec.source}: fused={rec.fused} contradicts why_not={rec.why_not!r}")
        return rec


class NotOffered(NamedTuple):
    """A source the caller did not offer to the arbitration this step, and why."""
    source: str
    why_not: str
    detail: str = ""


def _deg(rad: float) -> float | None:
    return math.degrees(rad) if rad is not None and math.isfinite(rad) else None


def _deg_0_360(rad: float) -> float | None:
    d = _deg(rad)
    if d is None:
        return None
    d %= 360.0
    return 0.0 if d >= 360.0 else d  # -1e-17 % 360 == 360.0 in floating point


def _sqrt_deg(var_rad2: float) -> float | None:
    return math.degrees(math.sqrt(var_rad2)) if math.isfinite(var_rad2) and var_rad2 >= 0.0 else None


def _num(v: float) -> float | None:
    return v if v is not None and math.isfinite(v) else None


def payload(rec: AidingRecord) -> dict:
    """The record at the edge (degrees; null where unknown): one entry of the Zenoh ``heading``
    topic's ``sources`` (service/schema/azimuthd.schema.json)."""
    return {"fused": rec.fused, "candidate": rec.candidate, "why_not": rec.why_not, "detail": rec.detail,
            "time_last_fused_s": _num(rec.time_last_fused_s),
            "observation_deg": _deg_0_360(rec.observation_rad),
            "observation_sigma_deg": _deg(rec.observation_sigma_rad),
            "innovation_deg": _deg(rec.innovation_rad),
            "innovation_sigma_deg": _sqrt_deg(rec.innovation_variance_rad2),
            "test_ratio": _num(rec.test_ratio),
            "source_innovation_deg": _deg(rec.source_innovation_rad),
            "source_innovation_sigma_deg": _sqrt_deg(rec.source_innovation_variance_rad2),
            "source_test_ratio": _num(rec.source_test_ratio)}


CSV_FIELDS = ("observation_deg", "observation_sigma_deg", "innovation_deg", "innovation_sigma_deg",
              "test_ratio", "fused", "time_last_fused_s", "why_not", "source_innovation_deg",
              "source_test_ratio")
"""Per-source CSV columns ``aid_<source>_<field>`` (replay), in this order."""


def csv_columns(sources=SOURCES) -> list[str]:
    return [f"aid_{s}_{f}" for s in sources for f in CSV_FIELDS]


def _cell(v: float | None) -> str:
    return "" if v is None or not math.isfinite(v) else format(v, ".12g")


def csv_row(records: dict, sources=SOURCES) -> list[str]:
    """The ``csv_columns`` cells of one row (``CSV_FIELDS`` per source): numbers in degrees (empty
    where unknown, 12 significant digits), fused 1/0, why_not its code; every cell empty for a
    source with no record. Written out field by field: replay writes one per output row."""
    out = []
    for s in sources:
        r = records.get(s)
        if r is None:
            out += [""] * len(CSV_FIELDS)
            continue
        out += [_cell(_deg_0_360(r.observation_rad)), _cell(_deg(r.observation_sigma_rad)),
                _cell(_deg(r.innovation_rad)), _cell(_sqrt_deg(r.innovation_variance_rad2)), _cell(r.test_ratio),
                "1" if r.fused else "0", _cell(r.time_last_fused_s), r.why_not, _cell(_deg(r.source_innovation_rad)),
                _cell(r.source_test_ratio)]
    return out
