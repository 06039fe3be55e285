"""The attachment on every sample, held to Zenoh's own serializer (zenoh-ext), which rmw_zenoh
writes it with."""

from __future__ import annotations

import pytest
import zenoh.ext as zext

from retriever.ros2.attachment import Attachment, decode, encode

GID = bytes(range(100, 116))


def test_the_layout_is_zenoh_ext_serialization_of_int64_int64_and_16_bytes():
    ours = encode(Attachment(7, 1_764_000_000_123_456_789, GID))
    theirs = zext.z_serialize((zext.Int64(7), zext.Int64(1_764_000_000_123_456_789), GID)).to_bytes()
    assert ours == theirs and len(ours) == 33
    assert decode(theirs) == Attachment(7, 1_764_000_000_123_456_789, GID)


def test_the_keyed_layout_of_earlier_releases_decodes_too():
    keyed = zext.z_serialize(("sequence_number", zext.Int64(3), "source_timestamp", zext.Int64(-1),
                              "source_gid", GID)).to_bytes()
    assert decode(keyed) == Attachment(3, -1, GID)


@pytest.mark.parametrize("data", [b"", b"\x00" * 32, b"\x0fsequence_numbe", bytes(33)])
def test_anything_else_is_refused(data):
    with pytest.raises(ValueError, match="rmw_zenoh attachment"):
        decode(data)
