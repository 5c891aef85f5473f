"""The user's signing key (where it is, made once and owner-only, refused when others may read it)
and the signed checkpoints: the header and HMAC computed here by hand, a changed or unsigned file
refused before anything is unpickled unless trusted, and --trust's adoption. Real files, a key of
each test's own (QDSEARCH_KEY)."""

import hashlib
import hmac
import os
import pickle
import re
import shutil
import stat
import tempfile
from pathlib import Path

import pytest

from qdsearch.base import signing
from qdsearch.base.flags import UsageError


@pytest.fixture
def key(tmp_path, monkeypatch) -> Path:
    path = tmp_path / "config" / "qdsearch" / "key"  # its folders made too
    monkeypatch.setenv(signing.KEY_VARIABLE, str(path))
    return path


def test_the_key_is_where_the_variable_or_the_config_folder_says(tmp_path, monkeypatch):
    monkeypatch.setenv(signing.KEY_VARIABLE, "~/my-key")
    monkeypatch.setenv("HOME", str(tmp_path))
    assert signing.key_path() == tmp_path / "my-key"
    monkeypatch.delenv(signing.KEY_VARIABLE)
    monkeypatch.setenv("XDG_CONFIG_HOME", str(tmp_path / "config"))
    assert signing.key_path() == tmp_path / "config" / "qdsearch" / "key"
    monkeypatch.delenv("XDG_CONFIG_HOME")
    assert signing.key_path() == tmp_path / ".config" / "qdsearch" / "key"


def test_the_key_is_made_once_owner_only(key):
    made = signing.user_key()
    assert len(made) == 32 and signing.user_key() == made
    assert key.read_text() == made.hex() + "\n"
    assert stat.S_IMODE(key.stat().st_mode) == 0o600 and stat.S_IMODE(key.parent.stat().st_mode) == 0o700
    assert os.listdir(key.parent) == ["key"]  # no temporary file left
    signing.make_key(key)  # another process's, too late: the first one stays
    assert signing.user_key() == made and os.listdir(key.parent) == ["key"]


def test_a_key_beside_another_filesystems_temporary_folder_is_made(monkeypatch):
    """The key is written to a temporary file in its own folder and linked in: a link across
    filesystems (a home apart from /tmp) would fail."""
    if os.stat("/dev/shm").st_dev == os.stat(tempfile.gettempdir()).st_dev:
        pytest.skip("/dev/shm is on the temporary folder's filesystem")
    folder = Path(tempfile.mkdtemp(dir="/dev/shm"))
    try:
        monkeypatch.setenv(signing.KEY_VARIABLE, str(folder / "key"))
        assert len(signing.user_key()) == 32 and os.listdir(folder) == ["key"]
    finally:
        shutil.rmtree(folder)


def test_a_key_that_cannot_be_made_or_read_is_refused_in_one_line(key):
    key.parent.mkdir(parents=True)
    (key.parent / "file").write_text("")
    blocked = key.parent / "file" / "key"
    said = f"cannot make the signing key {blocked}: File exists; set QDSEARCH_KEY to a key file you can write"
    with pytest.raises(UsageError, match=f"^{re.escape(said)}$"):
        signing.make_key(blocked)
    for text, mode, said in (
            ("ab" * 32, 0o644, f"{key}: other users may read or write this signing key; make it yours alone "
                               f"with chmod 600 {key}"),
            ("xyz", 0o600, f"{key}: not a readable signing key ("),
            ("ab" * 16, 0o600, f"{key}: not a signing key (64 hex digits); delete it to have a new one made "
                               "(the checkpoints it signed then need resume --trust)")):
        key.write_text(text)
        key.chmod(mode)
        with pytest.raises(UsageError) as caught:
            signing.user_key()
        assert str(caught.value).startswith(said), caught.value


def test_a_signed_pickle_is_its_header_hmac_and_pickle(key, tmp_path):
    path = tmp_path / "checkpoint.pkl"
    signing.write_signed_pickle(path, {"iteration": 3})
    payload = pickle.dumps({"iteration": 3}, protocol=pickle.HIGHEST_PROTOCOL)
    digest = hmac.new(signing.user_key(), signing.MAGIC + payload, hashlib.sha256).hexdigest()
    assert path.read_bytes() == b"qdsearch-signed-pickle/1 hmac-sha256\n" + digest.encode() + b"\n" + payload
    assert signing.check_signature(path.read_bytes()) == (payload, None)
    assert signing.read_signed_pickle(path, "a checkpoint") == {"iteration": 3}


def test_a_changed_or_unsigned_pickle_is_loaded_only_if_trusted(key, tmp_path, capsys):
    path = tmp_path / "checkpoint.pkl"
    signing.write_signed_pickle(path, [1, 2])
    data = path.read_bytes()
    changed = pickle.dumps([1, 3], protocol=pickle.HIGHEST_PROTOCOL)
    other = "signed with another key than yours (another user's or machine's), or changed since"
    for written, problem in (
            (data[:-len(changed)] + changed, other),
            (changed, "not signed (written before checkpoints were signed, or not by lunar_lander.py)")):
        path.write_bytes(written)
        assert signing.check_signature(written) == (changed, problem)
        with pytest.raises(UsageError) as caught:
            signing.read_signed_pickle(path, "a checkpoint")
        assert str(caught.value) == (f"{path}: {problem}; not loaded, as a pickle may run any code it holds; "
                                     f"{signing.trust_hint()} ({key})")
        assert signing.read_signed_pickle(path, "a checkpoint", trust=True) == [1, 3]
        signing.adopt(path)
        assert capsys.readouterr().out == f"{path}: trusted (--trust), and signed with your key\n"
        assert signing.read_signed_pickle(path, "a checkpoint") == [1, 3]
        signing.adopt(path)  # signed already: left as it is
        assert capsys.readouterr().out == ""
    signing.write_signed(path, b"not a pickle")
    said = f"{path}: not a readable checkpoint (UnpicklingError: "
    with pytest.raises(UsageError, match=f"^{re.escape(said)}"):
        signing.read_signed_pickle(path, "checkpoint")
    signing.adopt(tmp_path / "none.pkl")  # no checkpoint: nothing to adopt
    assert not (tmp_path / "none.pkl").exists()
