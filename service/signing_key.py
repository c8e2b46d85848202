"""The MAVLink 2 signing key: read once at start from a file only the daemon can read.

The key is the 32-byte secret of the MAVLink 2 signing protocol, shared with the flight
controller and the ground station. The file holds it as
- 64 hexadecimal characters (a trailing newline is fine): ``openssl rand -hex 32 > key``;
- or exactly 32 raw bytes: ``head -c 32 /dev/urandom > key``.
MAVProxy and Mission Planner derive the key from a passphrase as SHA-256(passphrase); the same key
in our format: ``printf %s 'passphrase' | sha256sum | cut -c1-64 > key``.

Checks, each failure a :class:`SigningKeyError` (a ConfigError: exit 2, systemd does not restart
a daemon whose key file is wrong) naming the file and the problem, never the key:
- the file is a regular file, checked on the opened descriptor (no check-then-open race);
- no permission bit for group or others (``chmod 600`` or ``400``): a key others can read is a
  key others can sign with;
- owned by the daemon's user or by root;
- 64 hex characters or 32 bytes, and not all zeros (MAVLink's "signing disabled" key).

Under systemd with ``DynamicUser=yes`` the daemon cannot read a root-owned file in /etc: pass it
with ``LoadCredential=mavlink_signing.key:/etc/azimuthd/mavlink_signing.key`` and set
``signing_key_file = "${CREDENTIALS_DIRECTORY}/mavlink_signing.key"``; systemd then presents a
copy owned by the service user, mode 0400, on a private tmpfs.

The key object never prints its bytes: ``repr`` and ``str`` give a fingerprint (the first 8 hex
digits of SHA-256 over a fixed label and the key) so an operator can check that two machines hold
the same key without showing it.
"""
from __future__ import annotations

import hashlib
import os
import stat
from pathlib import Path

from service.config import ConfigError

KEY_BYTES = 32
_MAX_FILE_BYTES = 256
_CRED_VAR = "${CREDENTIALS_DIRECTORY}"


class SigningKeyError(ConfigError):
    """The key file cannot be used; the message names the file and what is wrong."""


class SigningKey:
    """32 secret bytes that do not show themselves in logs, reprs or tracebacks' messages."""

    __slots__ = ("_secret",)

    def __init__(self, secret: bytes):
        if not isinstance(secret, (bytes, bytearray)) or len(secret) != KEY_BYTES:
            raise SigningKeyError(f"a MAVLink signing key is {KEY_BYTES} bytes")
        if not any(secret):
            raise SigningKeyError("an all-zero key means 'signing disabled' in MAVLink; generate a "
                                  "random one (openssl rand -hex 32)")
        self._secret = bytes(secret)

    @property
    def secret(self) -> bytes:
        """The key bytes, for the MAVLink link only."""
        return self._secret

    @property
    def fingerprint(self) -> str:
        return hashlib.sha256(b"azimuthd-signing-key-id:" + self._secret).hexdigest()[:8]

    def __repr__(self) -> str:
        return f"SigningKey(fingerprint={self.fingerprint})"

    __str__ = __repr__

    def __reduce__(self):  # never pickled into a worker process or a file by accident
        raise TypeError("SigningKey cannot be pickled")


def resolve_path(path: str, env: dict | None = None) -> Path:
    """``${CREDENTIALS_DIRECTORY}`` -> systemd's credentials directory (LoadCredential=)."""
    env = os.environ if env is None else env
    if _CRED_VAR in path:
        cred = env.get("CREDENTIALS_DIRECTORY")
        if not cred:
            raise SigningKeyError(f"{path}: CREDENTIALS_DIRECTORY is not set: the daemon was not started "
                                  "by systemd with LoadCredential= (see docs/SECURITY.md)")
        path = path.replace(_CRED_VAR, cred)
    return Path(path)


def parse_key(data: bytes) -> bytes:
    """File contents -> the 32 key bytes. The error never quotes the contents."""
    if len(data) == KEY_BYTES:
        if all(c in b"0123456789abcdefABCDEF" for c in data):
            raise SigningKeyError("holds 32 hexadecimal characters, a 16-byte key; a MAVLink signing key "
                                  "is 32 bytes = 64 hexadecimal characters")
        return data
    text = data.strip()
    if len(text) == 2 * KEY_BYTES:
        try:
            return bytes.fromhex(text.decode("ascii"))
        except (UnicodeDecodeError, ValueError):
            pass
    raise SigningKeyError(f"must hold 64 hexadecimal characters or exactly {KEY_BYTES} raw bytes "
                          f"(this file has {len(data)} bytes)")


def load_signing_key(path_text: str, env: dict | None = None) -> SigningKey:
    """Read and check the key file; SigningKeyError names the file and the problem."""
    path = resolve_path(path_text, env)
    try:
        fd = os.open(path, os.O_RDONLY | os.O_CLOEXEC | getattr(os, "O_NOCTTY", 0) | os.O_NONBLOCK)
    except FileNotFoundError:
        raise SigningKeyError(f"{path}: signing key file not found") from None
    except PermissionError:
        raise SigningKeyError(f"{path}: cannot read the signing key file (permission denied); under "
                              "systemd pass it with LoadCredential= (docs/SECURITY.md)") from None
    except OSError as exc:
        raise SigningKeyError(f"{path}: cannot open the signing key file ({exc.strerror})") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise SigningKeyError(f"{path}: the signing key must be a regular file")
        if st.st_mode & 0o077:
            raise SigningKeyError(f"{path}: permissions {stat.S_IMODE(st.st_mode):04o} let other users read "
                                  "the signing key; chmod 600 (or 400) it")
        euid = os.geteuid()
        if st.st_uid not in (euid, 0):
            raise SigningKeyError(f"{path}: owned by uid {st.st_uid}, not by the daemon's user ({euid}) or root")
        if st.st_size > _MAX_FILE_BYTES:
            raise SigningKeyError(f"{path}: {st.st_size} bytes is too long for a signing key file")
        data = os.read(fd, _MAX_FILE_BYTES + 1)
    except OSError as exc:
        raise SigningKeyError(f"{path}: cannot read the signing key file ({exc.strerror})") from None
    finally:
        os.close(fd)
    try:
        return SigningKey(parse_key(data))
    except SigningKeyError as exc:
        raise SigningKeyError(f"{path}: {exc}") from None
