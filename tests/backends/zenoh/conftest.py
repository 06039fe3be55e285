"""Fixtures shared by the Zenoh backend's tests."""

from __future__ import annotations

import pytest
import zenoh

from retriever.backends.zenoh.hub import peer_config


@pytest.fixture(scope="module")
def session():
    """An unconnected Zenoh peer session, one per test module, for node loops built by hand."""
    with zenoh.open(peer_config()) as s:
        yield s
