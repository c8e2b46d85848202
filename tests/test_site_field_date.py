"""The geomagnetic model's date when neither the config nor the log gives one (service.pipeline
decimal_year_now): today, not this second, so that a replay of a log without a date reproduces
itself and two Pipelines built minutes apart see the same Earth field."""
import datetime

import pytest

from service import pipeline
from service.config import validate

_REAL = datetime.datetime


def _clock_at(monkeypatch, when: datetime.datetime) -> None:
    class _Fixed(_REAL):
        @classmethod
        def now(cls, tz=None):
            return when if tz is None else when.astimezone(tz)
    monkeypatch.setattr(datetime, "datetime", _Fixed)


def _field(monkeypatch, when: datetime.datetime):
    _clock_at(monkeypatch, when)
    cfg = validate({"site": {"lat_deg": 47.397, "lon_deg": 8.546, "alt_m": 488.0}})
    assert cfg["site"]["decimal_year"] is None
    return pipeline.site_field(cfg).e_ned_gauss


def test_two_pipelines_on_one_day_see_the_same_field(monkeypatch):
    # GIVEN a site with no date WHEN the field is built at 08:00:00 and again at 17:42:31 UTC of the
    # same day THEN it is the same, bit for bit (it moved by 1e-9..1e-8 relative with the second)
    utc = datetime.timezone.utc
    a = _field(monkeypatch, _REAL(2026, 12, 2, 8, 0, 0, tzinfo=utc))
    b = _field(monkeypatch, _REAL(2026, 12, 2, 17, 42, 31, 250000, tzinfo=utc))
    assert (a == b).all()


def test_the_date_still_moves_the_field(monkeypatch):
    # GIVEN the same site WHEN a year has passed THEN the secular change is there (the date is used)
    utc = datetime.timezone.utc
    a = _field(monkeypatch, _REAL(2026, 12, 2, 8, 0, 0, tzinfo=utc))
    b = _field(monkeypatch, _REAL(2027, 12, 2, 8, 0, 0, tzinfo=utc))
    assert abs(b - a).max() > 1e-5   # gauss: ~tens of nT a year


def test_today_is_midnight_utc(monkeypatch):
    utc = datetime.timezone.utc
    _clock_at(monkeypatch, _REAL(2026, 1, 1, 23, 59, 59, tzinfo=utc))
    assert pipeline.decimal_year_now() == pytest.approx(2026.0, abs=0.0)
    _clock_at(monkeypatch, _REAL(2026, 7, 2, 12, 0, 0, tzinfo=utc))
    assert pipeline.decimal_year_now() == 2026 + 182 / 365
