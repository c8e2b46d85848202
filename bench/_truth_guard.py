"""Truth only scores: a ``sim.offline.SimRun`` with its truth sealed, for the decision half of a
bench (estimators, monitors, harness choices). Reading ``run.truth`` (any attribute) or the
scenario's true launcher azimuth from ``run.site`` raises ``TruthReadError``; the scoring half
gets the original run. tests/test_truth_isolation.py runs the benches' decision paths on sealed
runs, so a bench that decides from truth fails there."""
from __future__ import annotations

import dataclasses

TRUTH_SITE_KEYS = ("launcher_azimuth_deg",)
"""run.site keys that are truth, not operator configuration (the launcher's true azimuth is what
method A estimates; the site, date, launcher type/elevation and IMU mount are configured)."""


class TruthReadError(RuntimeError):
    """A decision path read the simulator's truth."""


class SealedTruth:
    def __init__(self, what: str = "run.truth"):
        object.__setattr__(self, "_what", what)

    def __getattr__(self, name):
        raise TruthReadError(f"{self._what}.{name} read before scoring: truth only scores")

    def __getitem__(self, key):
        raise TruthReadError(f"{self._what}[{key!r}] read before scoring: truth only scores")


class SealedSite(dict):
    def __missing__(self, key):
        if key in TRUTH_SITE_KEYS:
            raise TruthReadError(f"run.site[{key!r}] read before scoring: the true launcher azimuth is truth")
        raise KeyError(key)

    def get(self, key, default=None):
        if key in TRUTH_SITE_KEYS:
            raise TruthReadError(f"run.site[{key!r}] read before scoring: the true launcher azimuth is truth")
        return super().get(key, default)


def sealed(run):
    """A copy of ``run`` whose truth (and true launcher azimuth) cannot be read."""
    site = SealedSite({k: v for k, v in run.site.items() if k not in TRUTH_SITE_KEYS})
    return dataclasses.replace(run, truth=SealedTruth(), scenario=SealedTruth("run.scenario"), site=site)
