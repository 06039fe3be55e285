"""What the tests of retriever.ros2 share: a Zenoh router of their own."""

from __future__ import annotations

import json

import pytest
import zenoh

from retriever.backends.zenoh.hub import endpoint, free_port


@pytest.fixture
def router():
    """A Zenoh router listening on loopback, as rmw_zenohd does: (its session, its endpoint)."""
    at = endpoint(free_port())
    config = zenoh.Config()
    config.insert_json5("mode", '"router"')
    config.insert_json5("listen/endpoints", json.dumps([at]))
    config.insert_json5("scouting/multicast/enabled", "false")
    with zenoh.open(config) as session:
        yield session, at
