"""Config validation: every problem names its key; the example config documents every key."""
import re
import subprocess
import sys
from pathlib import Path

import pytest

from service.config import SPEC, ConfigError, load, state_dir, validate

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = ROOT / "systemd" / "azimuthd.toml"
MINIMAL = {"site": {"lat_deg": 45.0, "lon_deg": 7.0}}


def test_example_config_ships_no_site_and_the_start_says_so(tmp_path):
    """GIVEN the example config as shipped (no [site]: a wrong one gives a wrong heading) WHEN the
    daemon starts on it THEN it stops with exit 2 and one line naming the key and the fix."""
    out = subprocess.run([sys.executable, "-m", "service.cli", "run", "--config", str(EXAMPLE)],
                         capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert out.returncode == 2
    assert out.stderr.strip() == ("azimuthd: config error: site.lat_deg: required: the launch site is not set; "
                                  "set [site] lat_deg and lon_deg (or earth_field_ned_gauss) in the config "
                                  "(no default: a wrong site gives a wrong heading)")
    assert "Traceback" not in out.stderr + out.stdout


def test_example_config_loads_and_documents_every_key(tmp_path):
    with_site = tmp_path / "azimuthd.toml"
    with_site.write_text(EXAMPLE.read_text().replace("# lat_deg = 47.3769", "lat_deg = 47.3769")
                         .replace("# lon_deg = 8.5417", "lon_deg = 8.5417"))
    cfg = load(with_site)
    assert cfg["mavlink"]["component_id"] == 191
    text = EXAMPLE.read_text()
    for section, keys in SPEC.items():
        assert re.search(rf"^\[{section}\]", text, re.M), f"[{section}] missing from the example"
        for key in keys:
            # each key appears, set or commented out, with a comment line above it
            m = re.search(rf"^#? ?{key} = ", text, re.M)
            assert m, f"{section}.{key} not documented in {EXAMPLE.name}"
            before = text[:m.start()].rstrip("\n").splitlines()[-1]
            assert before.startswith("#"), f"{section}.{key} has no comment above it"


def test_defaults_filled_in():
    cfg = validate(MINIMAL)
    assert cfg["mavlink"]["url"] == "udpin:0.0.0.0:14550"
    assert cfg["launch"]["case"] == "inclined"
    assert cfg["outputs"]["extra_mavlink_urls"] == []


@pytest.mark.parametrize("raw, key, words", [
    ({"mavlink": {"imu_rate_hz": 5000}}, "mavlink.imu_rate_hz", "must be in [1, 1000], got 5000"),
    ({"mavlink": {"imu_rate_hz": "fast"}}, "mavlink.imu_rate_hz", "must be a number"),
    ({"mavlink": {"imu_rate_hz": True}}, "mavlink.imu_rate_hz", "must be a number"),
    ({"mavlink": {"url": "udp:nowhere"}}, "mavlink.url", ""),
    ({"mavlink": {"ulr": "udpin:0.0.0.0:1"}}, "mavlink.ulr", "unknown key"),
    ({"mavlnk": {}}, "mavlnk", "unknown section"),
    ({"launch": {"case": "sideways"}}, "launch.case", "must be one of vertical, inclined, aligned"),
    ({"site": {"lat_deg": 91.0, "lon_deg": 0.0}}, "site.lat_deg", "must be in [-90, 90]"),
    ({"site": {"lat_deg": 45.0}}, "site.lon_deg", "go together"),
    ({"site": {}}, "site.lat_deg", "required"),
    ({"site": {"earth_field_ned_gauss": [0.2, 0.0]}}, "site.earth_field_ned_gauss", "three finite numbers"),
    ({"outputs": {"extra_mavlink_urls": ["udpout:127.0.0.1:99999"]}}, "outputs.extra_mavlink_urls", "item 0"),
    ({"vehicle": {"name": "a/b"}}, "vehicle.name", "1..32 characters"),
])
def test_bad_values_name_the_key(raw, key, words):
    merged = {**MINIMAL, **raw} if "site" not in raw else raw
    with pytest.raises(ConfigError) as e:
        validate(merged)
    msg = str(e.value)
    assert msg.startswith(key + ":"), msg
    assert words in msg


def test_broken_files(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        load(tmp_path / "missing.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[mavlink\nurl = 3\n")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load(bad)
    binary = tmp_path / "bin.toml"
    binary.write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(ConfigError, match="not UTF-8"):
        load(binary)


def test_state_dir_precedence(monkeypatch, tmp_path):
    cfg = validate(MINIMAL)
    monkeypatch.setenv("STATE_DIRECTORY", str(tmp_path / "sd"))
    assert state_dir(cfg) == tmp_path / "sd"
    cfg["service"]["state_dir"] = str(tmp_path / "cfg")
    assert state_dir(cfg) == tmp_path / "cfg"
    monkeypatch.delenv("STATE_DIRECTORY")
    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path / "xdg"))
    cfg["service"]["state_dir"] = ""
    assert state_dir(cfg) == tmp_path / "xdg" / "azimuthd"


def test_cli_rejects_bad_config_with_exit_2(tmp_path):
    bad = tmp_path / "c.toml"
    bad.write_text('[mavlink]\nimu_rate_hz = -3\n[site]\nlat_deg = 1.0\nlon_deg = 2.0\n')
    p = subprocess.run([sys.executable, "-m", "service.cli", "run", "--config", str(bad)],
                       capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert p.returncode == 2
    assert "mavlink.imu_rate_hz: must be in [1, 1000], got -3" in p.stderr


def test_cli_version_and_help():
    p = subprocess.run([sys.executable, "-m", "service.cli", "--version"], capture_output=True, text=True,
                       timeout=60, cwd=ROOT)
    assert p.returncode == 0 and p.stdout.startswith("azimuthd ")
    p = subprocess.run([sys.executable, "-m", "service.cli", "--help"], capture_output=True, text=True,
                       timeout=60, cwd=ROOT)
    assert p.returncode == 0 and "run" in p.stdout and "sim" in p.stdout
    p = subprocess.run([sys.executable, "-m", "service.cli", "fly"], capture_output=True, text=True,
                       timeout=60, cwd=ROOT)
    assert p.returncode == 2 and "unknown command 'fly'" in p.stderr
