"""The compiled core is built and imported (a silently failed build must fail the suite), the
service selects it, ``AZIMUTHD_CORE=python`` selects the Python reference, and a core that cannot
be imported is said in one log line while the reference runs (an older extension without method B:
B runs its reference). pymavlink's CRC is fastcrc's."""
from __future__ import annotations

import logging

import pytest

from estimators import core, synthetic_ahrs
from service import core_backend
from estimators.strapdown import strapdown_step as reference_strapdown_step


def test_the_extension_is_built_and_imported():
    # GIVEN this install (make venv / make wheel build it) THEN the extension imported, no fallback
    assert core.AVAILABLE, core.IMPORT_ERROR
    from estimators import _core
    assert _core.__file__.endswith(".so") and hasattr(_core, "strapdown_propagate")
    assert core.B_AVAILABLE and hasattr(_core, "SyntheticAhrs")


def test_the_service_runs_the_core_by_default(monkeypatch):
    monkeypatch.delenv(core_backend.ENV, raising=False)
    b = core_backend.select()
    assert b.name == "core" and b.strapdown_step is core.strapdown_step_held
    assert b.synthetic_ahrs_step is core.synthetic_ahrs_step and b.synthetic_ahrs_unseen is core.synthetic_ahrs_unseen


def test_core_without_method_b_runs_b_in_python(monkeypatch, caplog):
    # GIVEN an extension built before method B was ported (no SyntheticAhrs) WHEN the service
    # selects THEN the core propagates, B runs its reference, and one warning line says so
    monkeypatch.setattr(core_backend, "_said", set())
    monkeypatch.setattr(core, "B_AVAILABLE", False)
    with caplog.at_level(logging.WARNING, logger="azimuthd.core"):
        b = core_backend.select({})
        core_backend.select({})
    assert b.name == "core" and b.strapdown_step is core.strapdown_step_held
    assert b.synthetic_ahrs_step is synthetic_ahrs.synthetic_ahrs_step
    assert [r.getMessage() for r in caplog.records] == [
        "compiled core without method B (an older build): B runs the Python reference"]


def test_python_reference_selectable(monkeypatch, caplog):
    # GIVEN AZIMUTHD_CORE=python WHEN selecting THEN the reference, said once
    monkeypatch.setattr(core_backend, "_said", set())
    with caplog.at_level(logging.INFO, logger="azimuthd.core"):
        b = core_backend.select({"AZIMUTHD_CORE": "python"})
        core_backend.select({"AZIMUTHD_CORE": "Python "})
    assert b.name == "python" and b.strapdown_step is reference_strapdown_step
    assert b.synthetic_ahrs_step is synthetic_ahrs.synthetic_ahrs_step
    assert [r.getMessage() for r in caplog.records] == ["AZIMUTHD_CORE=python: the Python reference runs the estimators"]


def test_bad_value_is_one_line_and_the_core_runs(monkeypatch, caplog):
    monkeypatch.setattr(core_backend, "_said", set())
    with caplog.at_level(logging.WARNING, logger="azimuthd.core"):
        b = core_backend.select({"AZIMUTHD_CORE": "fast"})
    assert b.name == "core"
    assert [r.getMessage() for r in caplog.records] == ["AZIMUTHD_CORE='fast' is not one of core, python: using core"]


def test_missing_core_is_one_log_line_and_the_reference_runs(monkeypatch, caplog):
    # GIVEN an install whose extension did not import WHEN the service selects THEN one warning
    # line naming why, and the Python reference (the daemon keeps running)
    monkeypatch.setattr(core_backend, "_said", set())
    monkeypatch.setattr(core, "AVAILABLE", False)
    monkeypatch.setattr(core, "IMPORT_ERROR", "ImportError: no module named estimators._core")
    with caplog.at_level(logging.WARNING, logger="azimuthd.core"):
        b = core_backend.select({})
        core_backend.select({})
    assert b.name == "python" and b.strapdown_step is reference_strapdown_step
    msgs = [r.getMessage() for r in caplog.records]
    assert msgs == ["compiled core not available (ImportError: no module named estimators._core): "
                    "the Python reference runs the estimators"]


def test_pymavlink_crc_is_fastcrc():
    # pymavlink's dialects take fastcrc's CRC-16/MCRF4XX when it imports (their x25crc is the fast class)
    import fastcrc
    from pymavlink.dialects.v20 import ardupilotmega, common
    for dialect in (ardupilotmega, common):
        assert dialect.mcrf4xx is fastcrc.crc16.mcrf4xx
        assert dialect.x25crc.__name__ == "_x25crc_fast"
    # and it is the MAVLink checksum: a known message packs to the slow class's CRC
    mav = ardupilotmega.MAVLink(None, srcSystem=1, srcComponent=191)
    buf = ardupilotmega.MAVLink_heartbeat_message(18, 8, 0, 0, 4, 3).pack(mav)
    crc = ardupilotmega._x25crc_slow(buf[1:-2])
    crc.accumulate(bytes([ardupilotmega.MAVLink_heartbeat_message.crc_extra]))
    assert int.from_bytes(buf[-2:], "little") == crc.crc


if __name__ == "__main__":
    raise SystemExit(pytest.main([__file__, "-q"]))
