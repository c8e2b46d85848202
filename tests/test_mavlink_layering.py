"""mavlink_io's place in the layering (DESIGN.md, Layout): it may import pymavlink and numpy, never
service, estimators or sim, not even for type checking. NavSolution lives in mavlink_io.navsolution
for that reason (service builds it, mavlink_io's encoders read it)."""
from __future__ import annotations

import ast
from pathlib import Path

import mavlink_io

FORBIDDEN = ("service", "estimators", "sim")


def _imported_packages(path: Path) -> set[tuple[str, int]]:
    out = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            out |= {(a.name.split(".")[0], node.lineno) for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            out.add((node.module.split(".")[0], node.lineno))
    return out


def test_mavlink_io_imports_nothing_above_it():
    # GIVEN every module of mavlink_io
    files = sorted(Path(mavlink_io.__file__).parent.glob("*.py"))
    assert len(files) >= 15
    # WHEN their import statements are read (TYPE_CHECKING blocks included: ast.walk sees them)
    bad = [f"{f.name}:{line} imports {pkg}" for f in files for pkg, line in _imported_packages(f)
           if pkg in FORBIDDEN]
    # THEN none reaches service, estimators or sim
    assert bad == []

