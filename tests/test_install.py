"""`make install` / `make upgrade` / `make uninstall` staged under a temporary DESTDIR (nothing is
written outside it but the build tree): the venv, the command, the unit, the example config and
the docs land where the unit points; the operator's config survives an upgrade and an uninstall;
the optional extras say how to get them when missing."""
from __future__ import annotations

import configparser
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def make(target: str, destdir: Path, *extra: str) -> subprocess.CompletedProcess:
    return subprocess.run(["make", "--no-print-directory", "-C", str(ROOT), target, f"DESTDIR={destdir}",
                           f"PYTHON={sys.executable}", *extra], capture_output=True, text=True, timeout=600)


def unit_documentation(unit: Path) -> list[str]:
    cp = configparser.ConfigParser(strict=False, interpolation=None)
    cp.optionxform = str
    cp.read_string(unit.read_text())
    return cp["Unit"]["Documentation"].split()


def test_install_upgrade_uninstall_in_a_staging_root(tmp_path):
    d = tmp_path / "root"
    dist = tmp_path / "dist"
    # GIVEN a staging root WHEN make install (the wheel built from this tree; dependencies not
    # fetched: the layout is under test, not pip)
    out = make("install", d, f"DIST={dist}", "PIP_OPTS=--no-deps")
    assert out.returncode == 0, out.stdout + out.stderr
    venv_cmd = d / "opt/azimuthd/bin/azimuthd"
    link = d / "usr/local/bin/azimuthd"
    unit = d / "etc/systemd/system/azimuthd.service"
    config = d / "etc/azimuthd/azimuthd.toml"
    docdir = d / "usr/local/share/doc/azimuthd"
    # THEN the command is the venv's, linked where the unit's ExecStart= runs it
    assert venv_cmd.is_file() and os.readlink(link) == "/opt/azimuthd/bin/azimuthd"
    assert unit.read_text() == (ROOT / "systemd/azimuthd.service").read_text()
    assert "ExecStart=/usr/local/bin/azimuthd run" in unit.read_text()
    assert config.read_text() == (ROOT / "systemd/azimuthd.toml").read_text()
    # every Documentation= of the unit is a file the install created
    docs = unit_documentation(unit)
    assert docs and all(u.startswith("file:///usr/local/share/doc/azimuthd/") for u in docs)
    for u in docs:
        assert (d / u.removeprefix("file:///")).is_file(), u
    assert (docdir / "VEHICLE.md").is_file() and (docdir / "azimuthd.toml").is_file()
    assert "next: set [site] and [mavlink] url" in out.stdout

    run = subprocess.run([str(venv_cmd), "--version"], capture_output=True, text=True, timeout=60)
    assert run.stdout.strip() == "azimuthd 0.1.0", run.stderr
    # the wheel carries the compiled core, built for this machine (it imports; numpy, which its
    # calls need, is a dependency not fetched here)
    core = subprocess.run([str(d / "opt/azimuthd/bin/python"), "-c",
                           "from estimators import _core; print(_core.LEVELLING_PACKED, _core.__file__.endswith('.so'))"],
                          capture_output=True, text=True, timeout=60, cwd=tmp_path)
    assert core.stdout.split() == ["38", "True"], core.stderr
    # the extras were not installed: each says how to get it, in one line, exit 2
    for args, words in ((["watch"], "pip install 'azimuthd[tui]'"),
                        (["replay", "x.tlog", "--plot", "p.png"], "pip install 'azimuthd[plot]'")):
        r = subprocess.run([str(venv_cmd), *args], capture_output=True, text=True, timeout=60, cwd=tmp_path)
        assert r.returncode == 2 and words in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr

    # WHEN the operator set the site and we upgrade THEN the config is kept, code and unit renewed
    config.write_text(config.read_text().replace("# lat_deg = 47.3769", "lat_deg = 45.0"))
    unit.write_text("stale")
    wheel = next(dist.glob("azimuthd-*.whl"))
    up = make("upgrade", d, f"WHEEL={wheel}", "PIP_OPTS=--no-deps --no-index")
    assert up.returncode == 0, up.stdout + up.stderr
    assert "lat_deg = 45.0" in config.read_text()
    assert unit.read_text() == (ROOT / "systemd/azimuthd.service").read_text()
    assert "upgraded to azimuthd 0.1.0; config and calibrations kept" in up.stdout

    # WHEN uninstalled THEN code, unit and docs are gone, the config stays (and it says so)
    rm = make("uninstall", d)
    assert rm.returncode == 0, rm.stdout + rm.stderr
    assert not (d / "opt/azimuthd").exists() and not link.is_symlink() and not unit.exists() and not docdir.exists()
    assert "lat_deg = 45.0" in config.read_text()
    assert "kept: /etc/azimuthd/" in rm.stdout


def test_upgrade_without_an_install_says_so(tmp_path):
    out = make("upgrade", tmp_path / "empty")
    assert out.returncode != 0
    assert "azimuthd is not installed in" in out.stdout + out.stderr and "run make install" in out.stdout + out.stderr
