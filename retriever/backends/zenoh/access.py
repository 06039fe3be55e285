"""Who may join a run, and what they may do there: Zenoh's own authentication and access control.

Every session of a run (the coordinator's hub and each worker) listens with Zenoh's user/password
authentication (``transport/auth/usrpwd``): a link is opened only by a peer that proves it knows
a password of the run's dictionary, so a process without the run's credentials gets no link to
any of its sessions and none of its messages arrive. Two users per run:

    retriever-run    the run's own processes: every message, both ways
    retriever-watch  a watcher: may subscribe (and see liveliness), never write. Each session's
                     access control (``access_control``) drops, on ingress from this user, every
                     put, delete, query, reply, queryable and liveliness token

Passwords are per run: random, or derived from a deployment secret (``secret=``, a file), so
that processes started elsewhere with the same secret can join (new_secret, ``retriever secret
new FILE``, writes a fresh one). A deployment's run derives them for its namespace *and its run
id* (``RunAccess.create(namespace, secret, run=...)``: HMAC(secret, "retriever/run/<ns>/<run>")):
the coordinator for its hub, each worker daemon for the flows of the run it prepared, from the
secret it holds and the run id of the prepare request (no password is ever sent). So a run's
password, or a watcher file, left behind by a killed run is worth nothing to any other run.
The namespace's own passwords (no ``run``: HMAC(secret, "retriever/run/<ns>")) are those of the
control links between a coordinator and the worker daemons (daemon/security.py), and of every
session of a deployment joined through a router, whose dictionary is fixed when it starts
(router.py). No session of one kind ever links to a session of the other: the daemons' and the
coordinator's control sessions link to each other only; the hub and the run's flows likewise.
The passwords reach the workers in the run's spec file, in the run's private directory (mode
0700); the dictionary file Zenoh reads is there too. A deployment's coordinator, whose sessions
alone read its dictionaries, gives Zenoh each in memory (SessionDictionary: on Linux no file on
disk, not even while a SIGKILLed ``retriever deploy`` starts).
A watcher gets a Zenoh config file of its own (JSON5, mode 0600) that holds the watcher's
password only: ``zenoh.Config.from_file(path)`` joins the hub, in client mode, read-only.

Zenoh authenticates the side that connects to the side that listens, not the other way round:
the user name of a link is known on its listening end only. So the access control cannot
``deny`` by default (the run's own links would be refused on their connecting end): it allows
by default and denies the watcher's writes, and a process with no password never gets a link.
"""

from __future__ import annotations

import hashlib
import hmac
import json
import os
import secrets
import stat
from dataclasses import dataclass
from pathlib import Path

from ...errors import AccessError
from .wire import KeySpace

RUN_USER = "retriever-run"
WATCH_USER = "retriever-watch"
#: the user a router links to another router as (router.py)
ROUTER_USER = "retriever-router"

#: what a watcher may not send: everything that writes, asks a queryable to run, or announces
WATCHER_MAY_NOT = ["put", "delete", "query", "reply", "declare_queryable", "liveliness_token", "liveliness_query"]

#: what a run's session never sends a watcher: the coordinator's control (ctl/run). The hub puts
#: it with congestion control BLOCK, which the workers need; to a watcher that stopped reading
#: (its link's queue full of the data it gets, dropped when congested: hub.forward_dropping),
#: such a put would wait up to Zenoh's `wait_before_close` (5 s), and the coordinator with it
#: (a `start` the workers got 5 s late). A watcher has no use for it.
WATCHER_UNSEEN = [KeySpace.every_control()]

#: the file, in a run's or a daemon's private folder, of the user:password lines Zenoh checks peers against
DICTIONARY = "zenoh-users.txt"

#: the name of a deployment's dictionary of the namespace's user:password lines, which its control
#: session checks the worker daemons against (in memory on Linux, SessionDictionary; else a file
#: in its run folder, removed once that session opened)
CONTROL_DICTIONARY = "zenoh-control-users.txt"

#: the fewest bytes a deployment secret file must hold
SECRET_MIN_BYTES = 16

#: the most bytes a deployment secret file may hold (read_secret reads no more than this)
SECRET_MAX_BYTES = 4096

#: the random bytes of a secret new_secret writes (as hex text: 64 characters and a newline)
SECRET_NEW_BYTES = 32


def read_secret(path: str | os.PathLike) -> bytes:
    """A deployment secret from its file, which only its owner may read.

    Only a regular file of at most SECRET_MAX_BYTES is read, and no more than that: a device
    (``/dev/zero``, read until memory ran out) or a FIFO (read forever) is refused by its stat,
    before anything opens it; a symlink is judged by what it names. The file is opened without
    blocking and checked again once open, so one swapped in between is refused too."""
    path = Path(path)
    try:
        st = path.stat()  # follows a symlink, but opens nothing: a FIFO's stat does not block
        _check_secret_file(path, st)
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_NOCTTY", 0))
        try:
            opened = os.fstat(fd)
            if (opened.st_dev, opened.st_ino) != (st.st_dev, st.st_ino):
                _check_secret_file(path, opened)
            with os.fdopen(fd, "rb", closefd=False) as f:
                raw = f.read(SECRET_MAX_BYTES + 1)
        finally:
            os.close(fd)
    except OSError as e:
        raise AccessError(f"cannot read the secret file {path}: {e.strerror}") from None
    if len(raw) > SECRET_MAX_BYTES:
        raise AccessError(f"the secret file {path} holds more than {SECRET_MAX_BYTES} bytes; a secret is "
                          f"{SECRET_MIN_BYTES} to {SECRET_MAX_BYTES}\n"
                          f"    hint: is it the right file? make a new one with: retriever secret new {path} --force")
    mode = st.st_mode
    data = raw.strip()
    if mode & 0o077:
        raise AccessError(f"the secret file {path} can be read by other users (mode {mode & 0o777:o})\n"
                          f"    hint: chmod 600 {path}")
    if len(data) < SECRET_MIN_BYTES:
        raise AccessError(f"the secret file {path} holds {len(data)} bytes; a secret needs at least "
                          f"{SECRET_MIN_BYTES}\n    hint: make a new one with: retriever secret new {path} --force")
    return data


def _check_secret_file(path: Path, st: os.stat_result) -> None:
    """Refuse, by its stat alone, a secret file that is no regular file or is too large to be one."""
    if not stat.S_ISREG(st.st_mode):
        raise AccessError(f"the secret file {path} is {_file_kind(st.st_mode)}; a secret is a regular file\n"
                          f"    hint: make one with: retriever secret new FILE")
    if st.st_size > SECRET_MAX_BYTES:
        raise AccessError(f"the secret file {path} holds {st.st_size} bytes; a secret is {SECRET_MIN_BYTES} "
                          f"to {SECRET_MAX_BYTES}\n"
                          f"    hint: is it the right file? make a new one with: retriever secret new {path} --force")


def _file_kind(mode: int) -> str:
    for test, kind in ((stat.S_ISDIR, "a folder"), (stat.S_ISCHR, "a character device"),
                       (stat.S_ISBLK, "a block device"), (stat.S_ISFIFO, "a FIFO"), (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return kind
    return f"no regular file (mode {mode:o})"


def new_secret(path: str | os.PathLike, overwrite: bool = False) -> Path:
    """Write a fresh deployment secret to ``path``: SECRET_NEW_BYTES random bytes (``secrets``)
    as hex text and a newline, which read_secret takes as it is (it strips the newline). The
    file is created mode 0600, whatever the umask, so it is never readable by others, not even
    for a moment. An existing file is refused unless ``overwrite``; then it is replaced at once
    (a new file moved over it), so a machine reading it sees the old secret or the new one."""
    path = Path(path)
    if path.is_dir():
        raise AccessError(f"cannot write the secret file {path}: it is a folder\n"
                          f"    hint: pass a file path, e.g. {path / 'deployment.key'}")
    if not path.parent.is_dir():
        raise AccessError(f"cannot write the secret file {path}: the folder {path.parent} does not exist\n"
                          f"    hint: mkdir -p {path.parent}")
    text = secrets.token_hex(SECRET_NEW_BYTES) + "\n"
    try:
        if overwrite:
            return write_private(path, text)
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except FileExistsError:
        raise AccessError(f"the secret file {path} already exists; a new secret would lock out every machine "
                          f"holding the old one\n    hint: pass --force (retriever secret new) or overwrite=True "
                          f"(new_secret) to replace it anyway") from None
    except OSError as e:
        raise AccessError(f"cannot write the secret file {path}: {e.strerror}") from None
    try:
        with os.fdopen(fd, "w", encoding="ascii") as f:
            os.fchmod(fd, 0o600)  # the umask may have taken the owner's own bits away
            f.write(text)
    except OSError as e:
        path.unlink(missing_ok=True)  # a part of a secret is no secret
        raise AccessError(f"cannot write the secret file {path}: {e.strerror}") from None
    return path


def secret_bytes(secret: str | os.PathLike | bytes | None) -> bytes | None:
    """The deployment secret: given as bytes, or as the path of a file holding it (read_secret)."""
    if secret is None or isinstance(secret, bytes):
        if secret is not None and len(secret) < SECRET_MIN_BYTES:
            raise AccessError(f"a secret needs at least {SECRET_MIN_BYTES} bytes, got {len(secret)}")
        return secret
    return read_secret(secret)


@dataclass(frozen=True)
class RunAccess:
    """A run's credentials: the password of its own processes and the watchers' password."""

    run_password: str
    watch_password: str

    @classmethod
    def create(cls, namespace: str, secret: bytes | None = None, run: str | None = None) -> RunAccess:
        """Fresh random passwords, or with ``secret`` the ones every holder of it derives for
        ``namespace`` and, if given, its ``run`` (a deployment's run id: the passwords of that
        run alone, see the module's docstring); a watcher's password tells nothing of the run's.
        A namespace holds no ``/`` (wire.check_chunk), so no two (namespace, run) give one text."""
        if secret is None:
            return cls(secrets.token_hex(32), secrets.token_hex(32))
        scope = namespace if run is None else f"{namespace}/{run}"

        def derive(role: str) -> str:
            return hmac.new(secret, f"retriever/{role}/{scope}".encode(), hashlib.sha256).hexdigest()

        return cls(derive("run"), derive("watch"))

    # -----------------------------------------------------------------------------------------
    # Files
    # -----------------------------------------------------------------------------------------
    def write_dictionary(self, directory: Path, name: str = DICTIONARY) -> Path:
        """The user:password lines Zenoh checks a connecting peer against (mode 0600), in file
        ``name`` of ``directory``."""
        return write_private(directory / name, self._dictionary_text())

    def session_dictionary(self, directory: Path, name: str = DICTIONARY) -> SessionDictionary:
        """The dictionary of a session of this process alone, which Zenoh reads once as the
        session opens: no file on disk where the system allows it (:class:`SessionDictionary`)."""
        return SessionDictionary(self._dictionary_text(), directory / name)

    def _dictionary_text(self) -> str:
        return f"{RUN_USER}:{self.run_password}\n{WATCH_USER}:{self.watch_password}\n"

    def write_watcher_config(self, path: Path, hub_endpoint: str, user: str = WATCH_USER) -> Path:
        """A Zenoh config (JSON5, mode 0600) with which ``zenoh.Config.from_file`` joins the
        hub as a read-only watcher; ``user``: the name it proves (a router's are per namespace:
        :func:`watch_user`)."""
        config = {
            "mode": "client",
            "connect": {"endpoints": [hub_endpoint]},
            "scouting": {"multicast": {"enabled": False}},
            "transport": {"auth": {"usrpwd": {"user": user, "password": self.watch_password}}},
        }
        text = ("// Watch a Retriever run, read-only: zenoh.Config.from_file(this file).\n"
                "// It holds the run's watcher password: keep it private.\n" + json.dumps(config, indent=2) + "\n")
        return write_private(path, text)

    # -----------------------------------------------------------------------------------------
    # Zenoh config of a run's own session
    # -----------------------------------------------------------------------------------------
    def session_config(self, dictionary_file: Path) -> dict[str, str]:
        """The entries (key → JSON5 value) that make a session one of the run's: it proves the
        run's password when it connects, checks every peer that connects to it, drops what a
        watcher sends, and sends a watcher none of the run's control (WATCHER_UNSEEN)."""
        usrpwd = {"user": RUN_USER, "password": self.run_password, "dictionary_file": str(dictionary_file)}
        acl = {
            "enabled": True,
            "default_permission": "allow",
            "rules": [{"id": "watchers_read_only", "messages": WATCHER_MAY_NOT, "flows": ["ingress"],
                       "permission": "deny", "key_exprs": ["**"]},
                      {"id": "watchers_see_no_control", "messages": ["put", "delete"], "flows": ["egress"],
                       "permission": "deny", "key_exprs": WATCHER_UNSEEN}],
            "subjects": [{"id": "watchers", "usernames": [WATCH_USER]}],
            "policies": [{"rules": ["watchers_read_only", "watchers_see_no_control"], "subjects": ["watchers"]}],
        }
        return {"transport/auth/usrpwd": json.dumps(usrpwd), "access_control": json.dumps(acl)}

    def client_config(self, namespace: str) -> dict[str, str]:
        """The entries (key → JSON5 value) with which a client session of ``namespace`` proves
        the run's password to a router (router.py): under :func:`run_user`'s name, since one
        router's dictionary holds the users of several namespaces."""
        return {"transport/auth/usrpwd": json.dumps({"user": run_user(namespace), "password": self.run_password})}

    def router_users(self, namespace: str) -> str:
        """The user:password lines a router's dictionary holds for ``namespace``: its run user
        and its watcher (:func:`run_user`, :func:`watch_user`)."""
        return f"{run_user(namespace)}:{self.run_password}\n{watch_user(namespace)}:{self.watch_password}\n"

    def to_spec(self, dictionary_file: Path) -> dict:
        return {"run_password": self.run_password, "watch_password": self.watch_password,
                "dictionary_file": str(dictionary_file)}

    @classmethod
    def from_spec(cls, spec: dict) -> tuple[RunAccess, Path]:
        return cls(spec["run_password"], spec["watch_password"]), Path(spec["dictionary_file"])


def run_user(namespace: str) -> str:
    """The user name of ``namespace``'s own processes at a router. A router admits several
    namespaces with one dictionary, which maps a user name to one password: so the name says
    the namespace. Peers check each other with a dictionary of their run's alone (RUN_USER)."""
    return f"{RUN_USER}.{namespace}"


def watch_user(namespace: str) -> str:
    """The user name of ``namespace``'s watchers at a router (see :func:`run_user`)."""
    return f"{WATCH_USER}.{namespace}"


def daemon_control_key(secret: bytes, namespace: str) -> bytes:
    """The key a coordinator seals its requests to ``namespace``'s worker daemons with, and each
    daemon checks them with (protocol/seal.py RequestSealer): derived from the secret itself, so
    that a holder of the namespace's passwords alone (every daemon's dictionary, every flow of a
    routed deployment) cannot make a request a daemon takes."""
    return hmac.new(secret, f"retriever/daemon-control/{namespace}".encode(), hashlib.sha256).digest()


def router_password(secret: bytes) -> str:
    """The password a router proves to another router it links to (ROUTER_USER): every holder
    of the secret derives the same, whatever namespaces it serves."""
    return hmac.new(secret, b"retriever/router", hashlib.sha256).hexdigest()


@dataclass(frozen=True)
class TlsFiles:
    """Mutual TLS on every link of a deployment (Zenoh's ``tls/`` endpoints): the CA that signs
    every certificate of the deployment, and this machine's certificate and key (PEM files). Each
    side of a link proves itself with its certificate, which must name the address it is reached
    at (subjectAltName); a peer without a certificate of that CA gets no link."""

    ca: str
    cert: str
    key: str

    @classmethod
    def of(cls, ca: object = None, cert: object = None, key: object = None) -> TlsFiles | None:
        """The three files (all or none given: None), each checked to be there."""
        given = {"--tls-ca": ca, "--tls-cert": cert, "--tls-key": key}
        if all(v is None for v in given.values()):
            return None
        missing = [flag for flag, v in given.items() if v is None]
        if missing:
            raise AccessError(f"TLS needs all of --tls-ca, --tls-cert and --tls-key; {', '.join(missing)} missing")
        for flag, path in given.items():
            if not os.path.isfile(str(path)):
                raise AccessError(f"{flag} {path}: no such file")
        return cls(*(os.path.abspath(str(v)) for v in given.values()))

    def session_config(self) -> dict[str, str]:
        """The config entries (key → JSON5 value) of a session whose links are all mutual TLS."""
        return {"transport/link/tls": json.dumps({
            "root_ca_certificate": self.ca, "enable_mtls": True,
            "listen_certificate": self.cert, "listen_private_key": self.key,
            "connect_certificate": self.cert, "connect_private_key": self.key})}

    def check_endpoints(self, endpoints) -> None:
        """A TLS deployment listens and connects on ``tls/`` endpoints only."""
        plain = [e for e in endpoints if not str(e).startswith("tls/")]
        if plain:
            raise AccessError(f"with TLS every endpoint is tls/HOST:PORT, not {', '.join(plain)}")


class SessionDictionary:
    """A dictionary (user:password lines) for a session this process opens: Zenoh reads it once,
    as the session opens, at ``path``. On Linux it is an anonymous memory file (``memfd_create``)
    named by ``/proc/self/fd/N``, which no other process of another user can open and which is gone
    when this process is, however it ends (a SIGKILL too: no password left on disk); elsewhere a
    file (mode 0600) at the path given. :meth:`close` once the session opened (the memory file
    closed, or the file removed)."""

    def __init__(self, text: str, fallback: Path):
        self._fd: int | None = None
        if hasattr(os, "memfd_create") and os.path.isdir("/proc/self/fd"):
            fd = os.memfd_create(f"retriever-{fallback.name}", getattr(os, "MFD_CLOEXEC", 0))
            try:
                data = text.encode()
                while data:
                    data = data[os.write(fd, data):]
            except BaseException:
                os.close(fd)
                raise
            self._fd, self.path = fd, Path(f"/proc/self/fd/{fd}")
        else:
            self.path = write_private(fallback, text)

    def close(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None
        else:
            self.path.unlink(missing_ok=True)


def write_private(path: Path, text: str) -> Path:
    """Write ``text`` to a new file only its owner can read (created so, never widened)."""
    tmp = path.with_name(path.name + ".tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    os.fchmod(fd, 0o600)  # a leftover .tmp keeps its mode through O_CREAT
    with os.fdopen(fd, "w", encoding="utf-8") as f:
        f.write(text)
    os.replace(tmp, path)
    return path
