"""Which implementation runs the ported estimator parts: the compiled core or the Python reference.

``AZIMUTHD_CORE`` (environment): ``core`` (the default) runs the compiled core (estimators._core via
estimators/core.py) where it is ported and proven equal; ``python`` runs the Python reference
everywhere. When the core cannot be imported (a failed build, a foreign platform) the service says
so in one log line and runs the reference: it never stops for it. Both give the same results
(tests/test_core_*.py), so the choice is speed, not behaviour.
"""
from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from typing import Callable

from estimators import core
from estimators.strapdown import strapdown_step as _strapdown_step_reference

log = logging.getLogger("azimuthd.core")

ENV = "AZIMUTHD_CORE"
CHOICES = ("core", "python")
_said: set[str] = set()


@dataclass(frozen=True)
class Backend:
    name: str
    """"core" or "python": what runs."""
    why: str
    """One line: why this one (the request, or why the core is not there)."""
    strapdown_step: Callable
    """The Pipeline's one gyro propagation (estimators.strapdown.strapdown_step's signature)."""


def _say(level: int, text: str) -> None:
    """Each distinct line once per process (a replay builds many Pipelines)."""
    if text not in _said:
        _said.add(text)
        log.log(level, text)


def select(environ=os.environ) -> Backend:
    """The backend for ``AZIMUTHD_CORE`` in ``environ``; one log line when it is not the core."""
    want = environ.get(ENV, "").strip().lower() or "core"
    if want not in CHOICES:
        _say(logging.WARNING, f"{ENV}={environ.get(ENV)!r} is not one of {', '.join(CHOICES)}: using core")
        want = "core"
    if want == "python":
        why = f"{ENV}=python: the Python reference runs the estimators"
        _say(logging.INFO, why)
        return Backend("python", why, _strapdown_step_reference)
    if not core.AVAILABLE:
        why = f"compiled core not available ({core.IMPORT_ERROR}): the Python reference runs the estimators"
        _say(logging.WARNING, why)
        return Backend("python", why, _strapdown_step_reference)
    return Backend("core", "compiled core (estimators._core)", core.strapdown_step_held)
