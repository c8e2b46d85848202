"""State files that survive crashes and say when they are damaged.

Every persisted calibration (method B's KF1 history, method D's deviation coefficients) is one
JSON document ``{"format", "version", "sha256", "payload"}``:
- written atomically: a temp file in the same directory, flush + fsync, ``os.replace`` over the
  old file, fsync of the directory. A crash leaves the old file or the new one, never half;
- checked on reading: the SHA-256 over the payload's canonical JSON and the format/version
  header. A truncated, corrupted or unknown file is renamed ``<name>.corrupt[.N]`` (kept for a
  post-mortem) and the caller starts without it instead of crashing.
"""
from __future__ import annotations

import hashlib
import json
import os
import pathlib


def checksum(payload: dict) -> str:
    canon = json.dumps(payload, sort_keys=True, separators=(",", ":"), allow_nan=False)
    return hashlib.sha256(canon.encode("utf-8")).hexdigest()


def document(fmt: str, version: int, payload: dict) -> dict:
    return {"format": fmt, "version": version, "sha256": checksum(payload), "payload": payload}


def payload_from_document(doc: object, fmt: str, version: int, what: str = "state") -> dict:
    """The payload of a parsed document; ValueError saying what is wrong."""
    if not isinstance(doc, dict) or doc.get("format") != fmt:
        raise ValueError(f"not an azimuthd {what} file")
    if doc.get("version") != version:
        raise ValueError(f"unsupported version {doc.get('version')!r}")
    payload = doc.get("payload")
    if not isinstance(payload, dict) or doc.get("sha256") != checksum(payload):
        raise ValueError("checksum mismatch (truncated or edited file)")
    return payload


def atomic_write_bytes(path: pathlib.Path, data: bytes) -> str:
    """Write ``data`` to ``path`` atomically; '' on success, else the error (nothing half-written)."""
    path = pathlib.Path(path)
    tmp = path.with_name(f".{path.name}.tmp.{os.getpid()}")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
        dfd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(dfd)
        finally:
            os.close(dfd)
    except OSError as exc:
        try:
            tmp.unlink()
        except OSError:
            pass
        return f"{type(exc).__name__}: {exc}"
    return ""


def set_aside(path: pathlib.Path) -> pathlib.Path:
    """Rename a damaged file to ``<name>.corrupt`` (or ``.corrupt.N``); returns the new path."""
    path = pathlib.Path(path)
    target = path.with_name(path.name + ".corrupt")
    n = 1
    while target.exists():
        target = path.with_name(f"{path.name}.corrupt.{n}")
        n += 1
    os.replace(path, target)
    return target


def remove_stale_temps(path: pathlib.Path) -> None:
    """Temp files left by a crash in the middle of a write."""
    path = pathlib.Path(path)
    for p in path.parent.glob(f".{path.name}.tmp.*"):
        try:
            p.unlink()
        except OSError:
            pass


def read_document(path: pathlib.Path, fmt: str, version: int, what: str = "state") -> tuple[dict | None, str]:
    """(payload, status): status is 'missing', 'loaded' or 'corrupt: <why>; moved to <path>'."""
    path = pathlib.Path(path)
    remove_stale_temps(path)
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        return None, "missing"
    try:
        return payload_from_document(json.loads(raw.decode("utf-8")), fmt, version, what), "loaded"
    except (ValueError, UnicodeDecodeError) as exc:  # JSONDecodeError is a ValueError
        return None, f"corrupt: {exc}; moved to {set_aside(path)}"


def write_document(path: pathlib.Path, fmt: str, version: int, payload: dict) -> str:
    data = json.dumps(document(fmt, version, payload), indent=1, allow_nan=False).encode("utf-8")
    return atomic_write_bytes(path, data)
