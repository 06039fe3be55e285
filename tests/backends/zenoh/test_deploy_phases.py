"""A deployment's timing hook (``on_phase``, deploy.Deployment): each step of its start, named, with
how long it took, also when that step fails.

A real daemon on loopback runs the deployment (killed by its pid at the end); a plain Zenoh session
with no worker behind it stands for a namespace where none is up.
"""

from __future__ import annotations

import pytest
import zenoh

from retriever import BackendError
from retriever.backends.zenoh.deploy import PHASES
from retriever.backends.zenoh.hub import endpoint, free_port, peer_config
from tests.backends.zenoh.test_daemon import namespace, workers  # noqa: F401 (fixtures)


def test_a_deployment_times_each_step_of_its_start_in_order(workers, namespace):  # noqa: F811
    from tests.deploy.deploy_flows import pipe

    port = free_port()
    workers("--name", "w", "--listen", endpoint(port), "--namespace", namespace, "--insecure",
            "--allow", "tests.deploy.deploy_flows").wait_started()
    timed: list[tuple[str, float]] = []
    try:
        pipe.run(duration=0.5, backend="zenoh", connect=[endpoint(port)], namespace=namespace, insecure=True,
                 quiet=True, on_phase=lambda name, seconds: timed.append((name, seconds)))
    finally:
        pipe.reset()
    assert [name for name, _ in timed] == list(PHASES) == ["join", "discover", "prepare"]
    assert all(seconds >= 0 for _, seconds in timed)


def test_the_step_that_fails_is_timed_too(namespace):  # noqa: F811
    from tests.deploy.deploy_flows import pipe

    port = free_port()
    timed: list[str] = []
    with zenoh.open(peer_config(listen=[endpoint(port)])):
        try:
            with pytest.raises(BackendError, match=f"no worker is up in namespace '{namespace}'"):
                pipe.run(duration=0.5, backend="zenoh", connect=[endpoint(port)], namespace=namespace,
                         insecure=True, quiet=True, on_phase=lambda name, seconds: timed.append(name))
        finally:
            pipe.reset()
    assert timed == ["join", "discover"]
