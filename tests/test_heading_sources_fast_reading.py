"""The heading sources' readings built without the frozen dataclass's __init__
(service/heading_sources._reading, the per-filter-step path) are SourceReading's own records.

GIVEN the arguments the sources pass (positional, keywords, the defaults, a tuple of groups, NaN
innovations), THEN ``_reading`` gives a record equal to ``SourceReading(...)`` with the same fields in
the same order, the same hash and repr, still frozen, and ``dataclasses.replace`` and ``groups`` work
on it; its parameters are SourceReading's fields with their defaults (a field added there fails here)."""
from __future__ import annotations

import dataclasses
import inspect
import math

import pytest

from service.heading_arbitration import SourceReading
from service.heading_sources import FC_REF_GROUP, MAG_GROUP, _reading

CASES = [
    (("azimuth", 1.0, 0.02, True, 10.0), {}),
    (("azimuth", 1.0, 0.03, True, 10.0, "", False, "disagrees with fc", "inconsistent"),
     dict(source_innovation_rad=0.2, source_innovation_variance_rad2=0.01, source_test_ratio=4.4)),
    (("synthetic_ahrs", 6.2, 0.05, False, 11.0, (MAG_GROUP, FC_REF_GROUP), True, "lost its reference"),
     dict(why_code="no_reference")),
    (("heading_filter", 0.5, math.sqrt(0.004), True, 12.0, MAG_GROUP, True, ""), {}),
    (("fc", 3.0, 0.1, True, 11.98, (MAG_GROUP, FC_REF_GROUP)), {}),
]


@pytest.mark.parametrize("args, kwargs", CASES)
def test_fast_reading_is_the_dataclass_record(args, kwargs):
    ref, fast = SourceReading(*args, **kwargs), _reading(*args, **kwargs)
    assert type(fast) is SourceReading and fast == ref and hash(fast) == hash(ref) and repr(fast) == repr(ref)
    assert list(vars(fast).items()) == list(vars(ref).items())
    assert fast.groups == ref.groups
    assert dataclasses.replace(fast, sigma_rad=1.0) == dataclasses.replace(ref, sigma_rad=1.0)
    with pytest.raises(dataclasses.FrozenInstanceError):
        fast.heading_rad = 0.0


def test_fast_reading_takes_every_field_with_its_default():
    params = inspect.signature(_reading).parameters
    fields = dataclasses.fields(SourceReading)
    assert list(params) == [f.name for f in fields]
    for f in fields:
        d = params[f.name].default
        if f.default is dataclasses.MISSING:
            assert d is inspect.Parameter.empty, f.name
        else:
            assert d == f.default or (math.isnan(d) and math.isnan(f.default)), f.name
