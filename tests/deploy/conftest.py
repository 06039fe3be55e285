"""The netns lab fixtures: one lab of three hosts per test session (tests/deploy/lab.py)."""

from __future__ import annotations

import pytest

from tests.deploy.lab import Lab, partitions_unavailable, reap_orphan_labs, unavailable


@pytest.fixture(scope="session")
def lab():
    """A lab of three hosts under a prefix of this session's, down at the session's end
    whatever happened; skips where no network namespace can be made."""
    if reason := unavailable():
        pytest.skip(reason)
    reap_orphan_labs()
    with Lab(3) as lab:
        yield lab


@pytest.fixture
def hosts(lab):
    """The lab's hosts, for one test: what it started there is stopped and its partitions
    healed when it ends, passed or failed."""
    yield lab.hosts
    lab.stop_processes()
    if not partitions_unavailable():
        for host in lab.hosts:
            lab.heal(host)


@pytest.fixture
def partitionable(lab):
    """The lab, for a test that partitions its hosts: skips, saying why, where nftables is missing."""
    if reason := partitions_unavailable():
        pytest.skip(reason)
    return lab
