"""A new deployment secret (access.new_secret, ``retriever secret new``): random, private from
the moment it exists, never written over by accident, and taken by read_secret as it is."""

from __future__ import annotations

import os
import stat
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

from retriever.backends.zenoh.access import (SECRET_MIN_BYTES, SECRET_NEW_BYTES, AccessError, new_secret,
                                             read_secret)


@contextmanager
def umask(mask: int) -> Iterator[None]:
    old = os.umask(mask)
    try:
        yield
    finally:
        os.umask(old)


def mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


def test_a_new_secret_is_private_even_under_a_permissive_umask(tmp_path):
    path = tmp_path / "lab.key"
    with umask(0):
        assert new_secret(path) == path
    assert mode(path) == 0o600
    text = path.read_text(encoding="ascii")
    assert len(text) == 2 * SECRET_NEW_BYTES + 1 and text.endswith("\n")
    assert len(bytes.fromhex(text)) == SECRET_NEW_BYTES  # hex text; fromhex skips the newline
    assert read_secret(path) == text.strip().encode()  # read as it is: no chmod, no edit
    assert len(read_secret(path)) >= SECRET_MIN_BYTES


def test_two_new_secrets_differ(tmp_path):
    assert new_secret(tmp_path / "a.key").read_text() != new_secret(tmp_path / "b.key").read_text()


def test_an_existing_file_is_kept_unless_overwrite(tmp_path):
    path = new_secret(tmp_path / "lab.key")
    old = path.read_text()
    with pytest.raises(AccessError, match=r"^the secret file .*lab\.key already exists; a new secret would lock out "
                                          r"every machine holding the old one\n    hint: pass --force"):
        new_secret(path)
    assert path.read_text() == old
    path.chmod(0o644)  # a file others could read is replaced by a private one
    with umask(0):
        new_secret(path, overwrite=True)
    assert path.read_text() != old
    assert mode(path) == 0o600
    assert sorted(p.name for p in tmp_path.iterdir()) == ["lab.key"]  # no temporary file left


def test_a_folder_is_refused(tmp_path):
    with pytest.raises(AccessError, match=r"^cannot write the secret file .*: it is a folder\n"
                                          r"    hint: pass a file path, e.g. .*deployment\.key$"):
        new_secret(tmp_path, overwrite=True)
    assert list(tmp_path.iterdir()) == []


def test_a_missing_folder_is_refused(tmp_path):
    path = tmp_path / "keys" / "lab.key"
    with pytest.raises(AccessError, match=r"^cannot write the secret file .*lab\.key: the folder .*keys does not "
                                          r"exist\n    hint: mkdir -p "):
        new_secret(path)
    assert not path.parent.exists()


def test_a_dangling_symlink_is_not_followed(tmp_path):
    """O_EXCL: the name is taken, even by a link to nowhere, so nothing is written through it."""
    target = tmp_path / "elsewhere"
    (tmp_path / "lab.key").symlink_to(target)
    with pytest.raises(AccessError, match=r"already exists"):
        new_secret(tmp_path / "lab.key")
    assert not target.exists()


def private_secret(path: Path, data: bytes) -> Path:
    path.write_bytes(data)
    path.chmod(0o600)
    return path


@pytest.mark.skipif(not os.path.exists("/dev/zero"), reason="needs /dev/zero")
def test_a_device_is_refused_before_it_is_read():
    # /dev/zero was read until the OOM killer came
    with pytest.raises(AccessError, match=r"^the secret file /dev/zero is a character device; a secret is a "
                                          r"regular file\n    hint: "):
        read_secret("/dev/zero")


def test_a_fifo_is_refused_without_opening_it(tmp_path):
    fifo = tmp_path / "lab.key"
    os.mkfifo(fifo, 0o600)
    # opening it to read would block until a writer came: the refusal comes from its stat
    with pytest.raises(AccessError, match=r"^the secret file .*lab\.key is a FIFO; a secret is a regular file\n"
                                          r"    hint: "):
        read_secret(fifo)


@pytest.mark.skipif(not os.path.exists("/dev/zero"), reason="needs /dev/zero")
def test_a_symlink_to_a_device_is_refused(tmp_path):
    link = tmp_path / "lab.key"
    link.symlink_to("/dev/zero")
    with pytest.raises(AccessError, match=r"^the secret file .*lab\.key is a character device; a secret is a "
                                          r"regular file\n"):
        read_secret(link)


def test_a_symlink_to_a_private_regular_file_is_read(tmp_path):
    target = private_secret(tmp_path / "real.key", b"k" * 32 + b"\n")
    link = tmp_path / "lab.key"
    link.symlink_to(target)  # how mounted secrets (Kubernetes, Docker) arrive
    assert read_secret(link) == b"k" * 32


def test_a_too_large_file_is_refused(tmp_path):
    from retriever.backends.zenoh.access import SECRET_MAX_BYTES
    path = private_secret(tmp_path / "lab.key", b"k" * (SECRET_MAX_BYTES + 1))
    with pytest.raises(AccessError, match=rf"^the secret file .*lab\.key holds {SECRET_MAX_BYTES + 1} bytes; a "
                                          rf"secret is {SECRET_MIN_BYTES} to {SECRET_MAX_BYTES}\n    hint: "):
        read_secret(path)
    assert read_secret(private_secret(path, b"k" * SECRET_MAX_BYTES)) == b"k" * SECRET_MAX_BYTES
