"""service/geofence_config.py: the [geofence] section, validated with errors naming the key."""
import pytest

from service.config import ConfigError
from service.geofence_config import KEYS, validate_geofence

SQUARE = [[47.0, 8.0], [47.0, 8.1], [47.1, 8.1], [47.1, 8.0]]


def ok(**kw):
    raw = {"enabled": True, "inclusion": [SQUARE]}
    raw.update(kw)
    return validate_geofence(raw)


def test_absent_or_disabled_is_none_but_still_validated():
    assert validate_geofence(None) is None
    assert validate_geofence({"enabled": False, "inclusion": [SQUARE]}) is None
    with pytest.raises(ConfigError, match=r"^geofence.margin_mm: unknown key"):
        validate_geofence({"enabled": False, "margin_mm": 3})


def test_defaults_and_closed_ring():
    cfg = ok(inclusion=[SQUARE + [SQUARE[0]]])
    assert cfg.inclusion == (tuple(tuple(v) for v in SQUARE),)  # the repeated closing vertex is dropped
    for key, (_t, default, _doc) in KEYS.items():
        if key not in ("enabled", "inclusion"):
            got = getattr(cfg, key)
            assert got == (tuple(default) if isinstance(default, list) else default), key


@pytest.mark.parametrize("raw, message", [
    ({"inclusion": [[[47.0, 8.0], [47.0, 8.1]]]}, "geofence.inclusion: polygon 0 must be a list of at least 3"),
    ({"inclusion": [[[47.0, 8.0], [47.0, 8.1], [47.1, "x"]]]}, "geofence.inclusion: polygon 0 vertex 2 must be"),
    ({"inclusion": [[[97.0, 8.0], [47.0, 8.1], [47.1, 8.1]]]}, "geofence.inclusion: polygon 0 vertex 0: latitude"),
    ({"exclusion": [[[47.0, 8.0], [47.1, 8.1], [47.0, 8.1], [47.1, 8.0]]]}, "geofence.exclusion: polygon 0 crosses itself"),
    ({"inclusion": [[[47.0, 8.0], [47.05, 8.0], [47.1, 8.0]]]}, r"geofence.inclusion: polygon 0 has \(almost\) no area"),
    ({"inclusion": [[[47.0, 8.0], [-47.0, 8.1], [47.1, 80.0]]]}, "spans more than 2000 km"),
    ({"margin_m": -1}, r"geofence.margin_m: must be in \[0, 100000\], got -1"),
    ({"lookahead_s": True}, "geofence.lookahead_s: must be a number, got True"),
    ({"actions": []}, "geofence.actions: must list at least one action"),
    ({"actions": ["rtl", "land"]}, "geofence.actions: item 1 must be one of rtl, rtl_mode"),
    ({"actions": ["rtl", "rtl"]}, "geofence.actions: lists an action twice"),
    ({"actions": ["terminate"]}, "needs the explicit opt-in geofence.allow_termination = true"),
    ({"actions": ["terminate", "rtl"], "allow_termination": True}, "'terminate' can only be the last action"),
    ({"actions": ["reposition"]}, "geofence.safe_lat_deg: 'reposition' needs safe_lat_deg and safe_lon_deg"),
    ({"safe_lat_deg": 47.0}, "geofence.safe_lon_deg: safe_lat_deg and safe_lon_deg go together"),
    ({"alt_min_m": 100.0, "alt_max_m": 110.0}, "geofence.alt_max_m: must exceed alt_min_m"),
    ({"wind_source": "gps"}, "geofence.wind_source: must be one of config, estimate"),
    ({"corridor_azimuth_deg": 400.0}, r"geofence.corridor_azimuth_deg: must be in \[0, 360\]"),
    ({"command_tries": 2.5}, "geofence.command_tries: must be an integer"),
])
def test_errors_name_the_key(raw, message):
    full = {"enabled": True, "inclusion": [SQUARE]}
    full.update(raw)
    with pytest.raises(ConfigError, match=message):
        validate_geofence(full)


def test_enabled_without_any_limit_is_an_error():
    with pytest.raises(ConfigError, match="geofence.enabled: the geofence is enabled but defines no limit"):
        validate_geofence({"enabled": True})
    assert validate_geofence({"enabled": True, "alt_max_m": 300.0}).alt_max_m == 300.0


def test_termination_opt_in_and_reposition_accepted():
    cfg = ok(actions=["reposition", "rtl", "terminate"], allow_termination=True, safe_lat_deg=47.05,
             safe_lon_deg=8.05)
    assert cfg.actions == ("reposition", "rtl", "terminate")


def test_the_documented_keys_are_in_docs():
    from pathlib import Path
    doc = (Path(__file__).resolve().parents[1] / "docs" / "GEOFENCE.md").read_text()
    missing = [k for k in KEYS if f"`{k}`" not in doc]
    assert not missing, f"docs/GEOFENCE.md does not document {missing}"
