"""`azimuthd replay LOG --config FILE`: the shipped config replays (it crashed on the absent
[geofence]); a broken config is one line, exit 2; --site overrides the config's and the log's site;
--exclude-fc-yaw reaches the Pipeline's config."""
import json
from pathlib import Path

import pytest

from service.replay import main
from test_logreaders_formats import new_dataflash

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def binlog(tmp_path_factory):
    p = tmp_path_factory.mktemp("cfg") / "f.bin"
    new_dataflash(p, [], seconds=1.0)
    return p


def _replay(capsys, *argv):
    rc = main([*map(str, argv), "--no-progress"])
    cap = capsys.readouterr()
    return rc, cap.out, cap.err


def test_shipped_config_replays(binlog, tmp_path, capsys):
    js = tmp_path / "s.json"
    rc, out, err = _replay(capsys, binlog, "--config", ROOT / "systemd" / "azimuthd.toml", "--site", "52.1,5.2",
                           "--json", js)
    assert rc == 0, err
    notes = json.loads(js.read_text())["config_notes"]
    assert any(n.startswith("config: ") and n.endswith("azimuthd.toml") for n in notes)
    # --site wins over the config's site and over the log's GPS fix
    assert "site from --site: 52.100000, 5.200000" in notes


@pytest.mark.parametrize("text,what", [
    ("[imu]\nstill_seconds = -1\n", "imu.still_seconds"),
    ("[imu\n", "not valid TOML"),
    ("[nosuch]\nx = 1\n", "nosuch: unknown section"),
    ("site = 3\n", "site: must be a table"),
    ("[geofence]\nenabled = true\ninclusion = [[[0, 0]]]\n", "geofence"),
])
def test_broken_config_is_one_line(binlog, tmp_path, capsys, text, what):
    cfg = tmp_path / "bad.toml"
    cfg.write_text(text)
    rc, out, err = _replay(capsys, binlog, "--config", cfg)
    assert rc == 2 and "config error" in err and what in err, err
    assert err.count("\n") == 1 and "Traceback" not in err and out == ""


def test_missing_config_and_a_directory(binlog, tmp_path, capsys):
    rc, _, err = _replay(capsys, binlog, "--config", tmp_path / "nope.toml")
    assert rc == 2 and "config file not found" in err
    rc, _, err = _replay(capsys, binlog, "--config", tmp_path)
    assert rc == 2 and err.count("\n") == 1


def test_exclude_fc_yaw_sets_the_key(binlog):
    from service.logreaders import open_log
    from service.replay import build_config

    class Args:
        config, site, exclude_fc_yaw = None, None, True
    cfg, notes = build_config(Args, open_log(binlog))
    assert cfg["heading"]["use_fc_yaw"] is False and any("--exclude-fc-yaw" in n for n in notes)
    Args.exclude_fc_yaw = False
    cfg, _ = build_config(Args, open_log(binlog))
    assert cfg["heading"].get("use_fc_yaw", True) is True
