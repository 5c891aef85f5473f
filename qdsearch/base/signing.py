"""Checkpoints signed with the user's own key, so that resume unpickles only what this user (or
their experiments, parts and jobs) wrote: a pickle runs code when it is loaded, and a run folder
may come from anyone.

A signed file is one header line, the HMAC-SHA256 (hex) of its payload under the user's key on a
second line, then the pickle's bytes: one file, written atomically, so no kill can part a
checkpoint from its signature. The key is 32 random bytes (as 64 hex digits), made on first use,
readable by its owner only, in $XDG_CONFIG_HOME/qdsearch/key (~/.config/qdsearch/key); QDSEARCH_KEY
names another key file (a cluster's nodes without a shared home share one that way).

Map:
- the key: `key_path`, `user_key` (`make_key`: race-free, any number of processes at once;
  `read_key`);
- signed pickles: `write_signed`, `check_signature`, `write_signed_pickle`, `read_signed_pickle`
  (the signature checked before anything is unpickled), `adopt` (resume --trust: a trusted file
  signed with the user's key).
"""

from __future__ import annotations

import contextlib
import hashlib
import hmac
import os
import pickle
import secrets
import stat
import tempfile
from pathlib import Path
from typing import Any

from qdsearch.base.flags import UsageError, named
from qdsearch.base.run_files import atomic_write, check_regular, read_regular, unpickle

KEY_VARIABLE = "QDSEARCH_KEY"  # a key file's path, in place of the user's config folder's
MAGIC = b"qdsearch-signed-pickle/1 hmac-sha256\n"  # a pickle never starts so (protocol 2+: 0x80)
DIGITS = 64  # the signature's hex digits (and the key file's)
def trust_hint() -> str:
    """What a refused checkpoint's message ends with."""
    return f"if you trust where it came from, resume with {named('trust')}, which signs it with your key"


def key_path() -> Path:
    """Where this user's key is: QDSEARCH_KEY, or qdsearch/key in the user's config folder."""
    if os.environ.get(KEY_VARIABLE):
        return Path(os.environ[KEY_VARIABLE]).expanduser()
    config = os.environ.get("XDG_CONFIG_HOME") or str(Path.home() / ".config")
    return Path(config) / "qdsearch" / "key"


def user_key() -> bytes:
    """This user's key, made on first use (a refusal, in one line, where it cannot be)."""
    path = key_path()
    if not path.exists():
        make_key(path)
    return read_key(path)


def make_key(path: Path) -> None:
    """A new key at `path`, its folder made owner-only. Many processes may make one at once (an
    experiment's parts): each writes its own to a temporary file and links it in; the first link
    wins, and every process then reads that one."""
    try:
        path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.")  # owner-only (0600)
        try:
            with os.fdopen(fd, "w") as file:
                file.write(secrets.token_hex(32) + "\n")
                file.flush()
                os.fsync(file.fileno())
            with contextlib.suppress(FileExistsError):  # another process's key is in: it is the one
                os.link(tmp, path)
        finally:
            os.unlink(tmp)
    except OSError as error:
        raise UsageError(f"cannot make the signing key {path}: {error.strerror or error}; set "
                         f"{KEY_VARIABLE} to a key file you can write") from None


def read_key(path: Path) -> bytes:
    """The key in `path`, a regular file which only its owner may read or write: its group and
    others may not (anyone but its owner could sign)."""
    if stat.S_IMODE(check_regular(path, "key").st_mode) & 0o077:  # a folder is named as one first
        raise UsageError(f"{path}: other users may read or write this signing key; make it "
                         f"yours alone with chmod 600 {path}")
    try:
        key = bytes.fromhex(read_regular(path, "key").decode("ascii").strip())
    except (ValueError, UnicodeDecodeError) as error:
        raise UsageError(f"{path}: not a readable signing key ({error})") from None
    if len(key) * 2 != DIGITS:
        raise UsageError(f"{path}: not a signing key ({DIGITS} hex digits); delete it to have a new "
                         f"one made (the checkpoints it signed then need resume {named('trust')})")
    return key


def signature(key: bytes, payload: bytes) -> bytes:
    return hmac.new(key, MAGIC + payload, hashlib.sha256).hexdigest().encode()


def write_signed(path: Path, payload: bytes) -> None:
    """`payload` with the header and its signature in front, written whole or not at all."""
    head = MAGIC + signature(user_key(), payload) + b"\n"
    atomic_write(path, lambda file: file.writelines([head, payload]))


def check_signature(data: bytes) -> tuple[bytes, str | None]:
    """A file's payload, and what is wrong with its signature (None: signed with this user's key)."""
    if not data.startswith(MAGIC):
        return data, "not signed (written before checkpoints were signed, or not by lunar_lander.py)"
    found, payload = data[len(MAGIC):len(MAGIC) + DIGITS], data[len(MAGIC) + DIGITS + 1:]
    if hmac.compare_digest(found, signature(user_key(), payload)):
        return payload, None
    return payload, "signed with another key than yours (another user's or machine's), or changed since"


def write_signed_pickle(path: Path, obj: Any) -> None:
    """`obj` pickled and signed, written whole or not at all."""
    write_signed(path, pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL))


def read_signed_pickle(path: Path, what: str, trust: bool = False) -> Any:
    """A signed pickle, unpickled only once its signature is found to be this user's (or the
    user trusts it: `trust`); else a one-line refusal that says why and how to accept it."""
    payload, problem = check_signature(read_regular(path, "checkpoint.pkl"))
    if problem and not trust:
        raise UsageError(f"{path}: {problem}; not loaded, as a pickle may run any code it holds; "
                         f"{trust_hint()} ({key_path()})")
    return unpickle(payload, path, what)


def adopt(path: Path) -> None:
    """Sign a checkpoint the user trusts (resume --trust) with their key, its payload as it was,
    and say so. The caller holds the folder's lock: no other process writes the file meanwhile."""
    if not path.is_file():
        return
    payload, problem = check_signature(read_regular(path, "checkpoint.pkl"))
    if problem:
        write_signed(path, payload)
        print(f"{path}: trusted ({named('trust')}), and signed with your key")
