"""A deployment's coordinator puts no dictionary on disk (issue 40 review, F2; access.SessionDictionary).

Its control session's dictionary holds the namespace's passwords, its hub's the run's; both were
once files in its run folder (/dev/shm/retriever-run-PID-...), removed as soon as the sessions had
opened, so that a ``retriever deploy`` SIGKILLed in between left them there until the next deploy.
Now Zenoh gets each from an anonymous memory file (/proc/self/fd/N), which it reads as the session
opens, in this process. A real daemon with a secret runs the deployment; every session the
coordinator opens is seen as it opens (the real ``zenoh.open``, called through): the run folder's
listing at that moment, and the dictionary path Zenoh is given.
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path

import pytest
import zenoh

from retriever.backends.zenoh.access import CONTROL_DICTIONARY, DICTIONARY, RunAccess
from retriever.backends.zenoh.folders import RUN_FOLDER
from retriever.backends.zenoh.hub import endpoint, free_port
from tests.backends.zenoh.test_daemon import SECRET, namespace, workers  # noqa: F401 (fixtures)

DICTIONARIES = {DICTIONARY, CONTROL_DICTIONARY}


def _run_folder_files() -> set[str]:
    """The files in this process's run folders, wherever they are made (/dev/shm, else the temporary folder)."""
    found = set()
    for base in {"/dev/shm", tempfile.gettempdir()}:
        for folder in Path(base).glob(f"{RUN_FOLDER}-{os.getpid()}-*"):
            found.update(p.name for p in folder.iterdir())
    return found


@pytest.mark.skipif(not hasattr(os, "memfd_create"), reason="no memfd_create: the dictionary is a file, removed")
def test_a_deployment_gives_zenoh_its_dictionaries_in_memory(workers, namespace, tmp_path, monkeypatch):  # noqa: F811
    from tests.deploy.deploy_flows import pipe

    secret = tmp_path / "secret"
    secret.write_text(SECRET)
    secret.chmod(0o600)
    port = free_port()
    workers("--name", "w", "--listen", endpoint(port), "--namespace", namespace, "--secret", str(secret),
            "--allow", "tests.deploy.deploy_flows").wait_started()
    opened: list[tuple[object, set[str]]] = []
    real_open = zenoh.open

    def seen_open(config, *args, **kwargs):
        try:
            usrpwd = json.loads(config.get_json("transport/auth/usrpwd"))
        except Exception:  # (no such entry: a session without a password)
            usrpwd = None
        opened.append((usrpwd, _run_folder_files()))
        return real_open(config, *args, **kwargs)

    monkeypatch.setattr(zenoh, "open", seen_open)
    try:
        pipe.run(duration=0.5, backend="zenoh", connect=[endpoint(port)], namespace=namespace,
                          secret=str(secret), quiet=True)
    finally:
        pipe.reset()
    dictionaries = [usrpwd["dictionary_file"] for usrpwd, _ in opened
                    if isinstance(usrpwd, dict) and "dictionary_file" in usrpwd]
    assert len(dictionaries) >= 2, opened  # the control session's and the hub's
    assert all(path.startswith("/proc/self/fd/") for path in dictionaries), dictionaries
    for _, files in opened:
        assert not files & DICTIONARIES, f"a dictionary file in the run folder as a session opened: {files}"


def test_a_session_dictionary_holds_the_users_and_is_no_file_in_the_folder(tmp_path):
    access = RunAccess.create("lab", SECRET.encode(), run="r1")
    dictionary = access.session_dictionary(tmp_path)
    try:
        assert dictionary.path.read_text() == (f"retriever-run:{access.run_password}\n"
                                               f"retriever-watch:{access.watch_password}\n")
        if hasattr(os, "memfd_create"):
            assert str(dictionary.path).startswith("/proc/self/fd/") and list(tmp_path.iterdir()) == []
    finally:
        dictionary.close()
    assert list(tmp_path.iterdir()) == []
