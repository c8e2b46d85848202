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


def test_a_log_whose_fc_yaw_came_from_our_odometry_excludes_it_by_itself(binlog):
    """GIVEN a DataFlash log whose parameters say EKF3 fused our ODOMETRY yaw (VISO_TYPE 1,
    EK3_SRC1_YAW 6, EK2_ENABLE 0: an ArduPlane flight with azimuthd feeding the FC) WHEN it is
    replayed without --exclude-fc-yaw THEN the FC's yaw is excluded with the reason, as the daemon
    decides it live (comparing our heading with the FC's would compare it with itself); the real
    RTL log (VISO_TYPE 0) and a PX4 log with EKF2_EV_CTRL's yaw bit off keep it."""
    from service.logreaders import LogSummary, open_log
    from service.replay import build_config, fc_yaw_from_our_odometry

    class Args:
        config, site, exclude_fc_yaw = None, None, False
    data = Path(__file__).resolve().parents[1].parent / "shared" / "data"
    rtl = (data if data.is_dir() else Path("/work/shared/data")) / "arducopter-rtl-midflight.bin"
    if rtl.exists():
        reader = open_log(rtl)
        assert reader.summary.params.get("VISO_TYPE") == 0.0  # the real log's own parameters were read
        assert fc_yaw_from_our_odometry(reader.summary) is None
        cfg, notes = build_config(Args, reader)
        assert cfg["heading"].get("use_fc_yaw", True) is True and not any("ODOMETRY" in n for n in notes)
    reader = open_log(binlog)
    assert reader.summary.params == {}  # a log with no PARM records claims nothing
    cfg, _ = build_config(Args, reader)
    assert cfg["heading"].get("use_fc_yaw", True) is True

    ours = {f"EK3_SRC{n}_{k}": 0.0 for n in (1, 2, 3) for k in ("POSXY", "VELXY", "POSZ", "VELZ", "YAW")}
    ours.update(VISO_TYPE=1.0, EK2_ENABLE=0.0, EK3_ENABLE=1.0, EK3_SRC1_YAW=6.0, EK3_SRC1_POSZ=1.0)
    reader.summary.params = ours
    why = fc_yaw_from_our_odometry(reader.summary)
    assert why is not None and "EK3_SRC1_YAW 6" in why
    cfg, notes = build_config(Args, reader)
    assert cfg["heading"]["use_fc_yaw"] is False and any("came from our ODOMETRY" in n for n in notes)
    assert fc_yaw_from_our_odometry(LogSummary("ulog", "px4", params={"EKF2_EV_CTRL": 0.0})) is None
    assert "yaw comes from our ODOMETRY" in fc_yaw_from_our_odometry(
        LogSummary("ulog", "px4", params={"EKF2_EV_CTRL": 8.0}))
    assert fc_yaw_from_our_odometry(LogSummary("tlog")) is None  # no parameters: nothing claimed
