"""The private folders of runs and daemons, named by their process, and reaped once it is gone
(issue 40, item 8; folders.py).

A SIGKILLed `retriever deploy` left its run folder in /dev/shm for good, with the deployment's
password file in it. The deploy here is a real process against a real daemon on loopback; it is
killed by its pid, and so is every process a test starts.
"""

from __future__ import annotations

import os
import shutil
import signal
import stat
import subprocess
import sys
import time
from pathlib import Path

import pytest
import zenoh

from retriever.backends.zenoh.access import DICTIONARY
from retriever.backends.zenoh.coordinator import run_dir
from retriever.backends.zenoh.daemon import ask, open_access
from retriever.backends.zenoh.folders import RUN_FOLDER, private_folder, reap_stale
from retriever.backends.zenoh.hub import endpoint, free_port, peer_config
from retriever.backends.zenoh.protocol import InfoRequest
from tests.backends.zenoh.test_daemon import BOUND_S, ROOT, SECRET, _cli, _env, namespace, workers  # noqa: F401


def _dead_pid() -> int:
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    return gone.pid


def test_the_folders_of_gone_processes_are_reaped_those_of_live_ones_and_other_users_kept(tmp_path):
    dead = tmp_path / f"{RUN_FOLDER}-{_dead_pid()}-abc"
    alive = tmp_path / f"{RUN_FOLDER}-{os.getpid()}-abc"
    odd = tmp_path / f"{RUN_FOLDER}-notapid-abc"
    other_kind = tmp_path / f"retriever-worker-{_dead_pid()}-abc"
    for folder in (dead, alive, odd, other_kind):
        folder.mkdir()
    (dead / DICTIONARY).write_text("retriever-run:password\n")
    made = private_folder(RUN_FOLDER, str(tmp_path))
    assert made.name.startswith(f"{RUN_FOLDER}-{os.getpid()}-")
    assert stat.S_IMODE(made.stat().st_mode) == 0o700
    assert not dead.exists()
    assert alive.exists() and odd.exists() and other_kind.exists()
    assert reap_stale(RUN_FOLDER, str(tmp_path)) == []


def test_a_runs_folder_is_named_by_its_process():
    folder = run_dir()
    try:
        assert folder.name.startswith(f"{RUN_FOLDER}-{os.getpid()}-"), folder
    finally:
        folder.rmdir()


def _shm_folders(pid: int) -> list[Path]:
    return sorted(Path("/dev/shm").glob(f"{RUN_FOLDER}-{pid}-*"))


def _until(condition, what: str) -> None:
    give_up = time.monotonic() + BOUND_S
    while not condition():
        assert time.monotonic() < give_up, f"not within {BOUND_S:g} s: {what}"
        time.sleep(0.1)


@pytest.mark.skipif(not os.path.isdir("/dev/shm"), reason="run folders go to /dev/shm where there is one")
def test_a_sigkilled_deploy_leaves_no_password_and_the_next_run_reaps_its_folder(workers, namespace, tmp_path):  # noqa: F811
    secret = tmp_path / "lab.key"
    secret.write_text(SECRET)
    secret.chmod(0o600)
    port = free_port()
    workers("--name", "w", "--listen", endpoint(port), "--namespace", namespace, "--secret", str(secret),
            "--path", str(ROOT / "tests" / "deploy")).wait_started()
    deploy = subprocess.Popen([sys.executable, "-m", "retriever.cli", "deploy", "tests/deploy/deploy_flows.py:pipe",
                               "--connect", endpoint(port), "--namespace", namespace, "--secret", str(secret),
                               "--duration", "600"], cwd=ROOT, env=_env(),
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        with open_access(namespace, str(secret)) as access:
            config = peer_config(connect=[endpoint(port)], access=access)
            config.insert_json5("mode", '"client"')
            with zenoh.open(config) as session:
                _until(lambda: ask(session, namespace, "w", InfoRequest()).nodes, "the deployment's flows run")
                [stale] = _shm_folders(deploy.pid)
                assert not (stale / DICTIONARY).exists(), "the deployment's password file is still on disk"
                deploy.send_signal(signal.SIGKILL)
                deploy.wait(BOUND_S)
                assert stale.exists()  # no one removed it: its process could not
                _until(lambda: not ask(session, namespace, "w", InfoRequest()).nodes,
                       "the worker stopped the flows of its coordinator gone")
        done = _cli("deploy", "tests/deploy/deploy_flows.py:pipe", "--connect", endpoint(port), "--namespace",
                    namespace, "--secret", str(secret), "--duration", "1")
        assert done.returncode == 0, done.stderr
        assert not stale.exists(), "the next run did not reap the folder of the killed one"
    finally:
        if deploy.poll() is None:
            deploy.kill()
            deploy.wait()
        for leftover in _shm_folders(deploy.pid):  # what the test made, it removes, whatever happened
            shutil.rmtree(leftover, ignore_errors=True)
