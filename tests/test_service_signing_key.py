"""The signing key file: formats, permission checks, clear errors that never show the key."""
from __future__ import annotations

import base64
import hashlib
import os
import pickle
import shutil
import subprocess
import sys

import pytest

from service.config import ConfigError
from service.signing_key import SigningKey, SigningKeyError, load_signing_key

KEY = bytes(range(1, 33))


def _forms(key: bytes) -> list[bytes]:
    """Ways a key could leak into text: raw, hex (both cases), base64."""
    return [key, key.hex().encode(), key.hex().upper().encode(), base64.b64encode(key)]


def _write(path, data: bytes, mode: int = 0o600):
    path.write_bytes(data)
    os.chmod(path, mode)
    return path


def test_hex_file_with_newline_and_raw_file_give_the_same_key(tmp_path):
    a = load_signing_key(str(_write(tmp_path / "hex", KEY.hex().encode() + b"\n")))
    b = load_signing_key(str(_write(tmp_path / "raw", KEY, 0o400)))
    assert a.secret == b.secret == KEY
    assert a.fingerprint == b.fingerprint and len(a.fingerprint) == 8


def test_mavproxy_passphrase_recipe_gives_sha256_of_the_passphrase(tmp_path):
    # docs: printf %s 'passphrase' | sha256sum | cut -c1-64 > key
    digest_hex = hashlib.sha256(b"correct horse").hexdigest()
    k = load_signing_key(str(_write(tmp_path / "k", digest_hex.encode() + b"\n")))
    assert k.secret == hashlib.sha256(b"correct horse").digest()


@pytest.mark.parametrize("mode", [0o644, 0o640, 0o604, 0o660, 0o606])
def test_group_or_world_access_is_refused(tmp_path, mode):
    p = _write(tmp_path / "k", KEY.hex().encode(), mode)
    with pytest.raises(SigningKeyError, match=f"permissions {mode:04o}.*chmod 600"):
        load_signing_key(str(p))


@pytest.mark.parametrize("content, why", [
    (b"", "64 hexadecimal characters"),
    (KEY.hex()[:62].encode(), "64 hexadecimal characters"),
    (("zz" + KEY.hex()[2:]).encode(), "64 hexadecimal characters"),
    (KEY[:16].hex().encode(), "16-byte key"),
    (bytes(32), "all-zero"),
    (b"0" * 64, "all-zero"),
    (KEY + b"x", "64 hexadecimal characters"),
])
def test_bad_contents_are_refused_without_quoting_them(tmp_path, content, why):
    p = _write(tmp_path / "k", content)
    with pytest.raises(SigningKeyError, match=why) as ei:
        load_signing_key(str(p))
    msg = str(ei.value).encode()
    assert str(p).encode() in msg
    for form in _forms(content[:32]) if len(content) >= 8 else []:
        assert form not in msg


def test_missing_directory_and_oversized_files(tmp_path):
    with pytest.raises(SigningKeyError, match="not found"):
        load_signing_key(str(tmp_path / "nope"))
    d = tmp_path / "dir"
    d.mkdir(mode=0o700)
    with pytest.raises(SigningKeyError, match="regular file"):
        load_signing_key(str(d))
    big = _write(tmp_path / "big", b"a" * 1000)
    with pytest.raises(SigningKeyError, match="too long"):
        load_signing_key(str(big))
    assert issubclass(SigningKeyError, ConfigError)  # the CLI's exit 2, systemd does not restart


@pytest.mark.skipif(os.geteuid() != 0, reason="chown to another user needs root")
def test_a_file_owned_by_another_user_is_refused(tmp_path):
    p = _write(tmp_path / "k", KEY.hex().encode())
    os.chown(p, 65534, 65534)
    with pytest.raises(SigningKeyError, match="owned by uid 65534"):
        load_signing_key(str(p))


def test_a_symlink_is_checked_on_its_target(tmp_path):
    target = _write(tmp_path / "k", KEY.hex().encode())
    link = tmp_path / "link"
    link.symlink_to(target)
    assert load_signing_key(str(link)).secret == KEY
    os.chmod(target, 0o644)
    with pytest.raises(SigningKeyError, match="permissions 0644"):
        load_signing_key(str(link))


def test_credentials_directory_expansion(tmp_path):
    cred = tmp_path / "creds"
    cred.mkdir()
    _write(cred / "mavlink_signing.key", KEY.hex().encode(), 0o400)
    spec = "${CREDENTIALS_DIRECTORY}/mavlink_signing.key"
    assert load_signing_key(spec, env={"CREDENTIALS_DIRECTORY": str(cred)}).secret == KEY
    with pytest.raises(SigningKeyError, match="CREDENTIALS_DIRECTORY is not set.*LoadCredential"):
        load_signing_key(spec, env={})


def test_the_key_object_never_shows_its_bytes():
    k = SigningKey(KEY)
    for text in (repr(k), str(k), f"{k}", f"{k!r}"):
        for form in _forms(KEY):
            assert form.decode("latin-1") not in text
        assert k.fingerprint in text
    with pytest.raises(TypeError):
        pickle.dumps(k)
    with pytest.raises(SigningKeyError):
        SigningKey(KEY[:31])


@pytest.mark.skipif(os.geteuid() != 0 or shutil.which("setpriv") is None,
                    reason="needs root and setpriv to run as an unprivileged user")
def test_unprivileged_daemon_user_cannot_read_a_root_only_key_and_is_told_how(tmp_path):
    """What happens under DynamicUser with a key in /etc owned by root: a clear hint to
    LoadCredential=, not a traceback."""
    os.chmod(tmp_path, 0o755)
    p = _write(tmp_path / "k", KEY.hex().encode())  # root:root 0600
    code = ("import sys; from service.signing_key import load_signing_key, SigningKeyError\n"
            f"try:\n    load_signing_key({str(p)!r})\nexcept SigningKeyError as e:\n    print(e); sys.exit(3)\n")
    r = subprocess.run(["setpriv", "--reuid=65534", "--regid=65534", "--clear-groups", "--no-new-privs",
                        sys.executable, "-c", code], capture_output=True, text=True, timeout=60,
                       cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    assert r.returncode == 3, r.stderr
    assert "permission denied" in r.stdout and "LoadCredential" in r.stdout
