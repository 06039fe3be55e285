"""Decoding never runs code (issue 17 §1): a value naming ``os:system`` reaches every entry point
that decodes values — the codec, the wire (data messages and reports), the hand-over state file
of a restarting flow, an IR parameter, a log (``read_log().trace()``, ``retriever log cat``,
``retriever replay``) — and each refuses it, or shows it inert, without running the command: a
marker file the command would create stays absent.

The zenoh runtime's end-to-end case (a message published into a live run) is in
``tests/backends/zenoh/test_access.py``.
"""

from __future__ import annotations

import base64
import json
import subprocess
import sys
import textwrap
from pathlib import Path

import msgpack
import pytest

from retriever import CodecError, LogError, read_log
from retriever.backends.zenoh.protocol import Report, decode_handover_state
from retriever.backends.zenoh.wire import WIRE_VERSION, WireError, decode_data
from retriever.codec import EXT_DATACLASS, UnregisteredValue, packb, unpackb, unpackb_out_of_band
from tests.log.helpers import ROOT, cli, cli_env
from tests.log.log_flows import build_small

#: callables a forged value names; each would create the marker file if it were ever called
TARGETS = ["os:system", "posix:system", "subprocess:getoutput", "builtins:exec", "pathlib:Path.touch"]


def forged(path: str, marker: Path) -> bytes:
    """A msgpack extension-4 value ("a dataclass") naming ``path`` with arguments that create ``marker``."""
    fields = {"command": f"touch {marker}", "cmd": f"touch {marker}", "source": f"open({str(marker)!r}, 'w')",
              "self": str(marker)}
    return msgpack.packb(msgpack.ExtType(EXT_DATACLASS, msgpack.packb([path, fields], use_bin_type=True)))


@pytest.fixture
def marker(tmp_path: Path) -> Path:
    path = tmp_path / "pwned"
    yield path
    assert not path.exists(), "a decoded value ran code"


# ---------------------------------------------------------------------------------------------
# The codec
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("target", TARGETS)
def test_the_codec_refuses_a_value_naming_an_unregistered_callable(target, marker):
    with pytest.raises(CodecError, match=rf"cannot decode a value of type '{target}': no value type of that name "
                                         "is registered in this process, and decoding never imports or calls"):
        unpackb(forged(target, marker))


@pytest.mark.parametrize("target", TARGETS)
def test_tools_that_show_values_keep_them_inert(target, marker):
    value = unpackb(forged(target, marker), keep_unregistered=True)
    assert type(value) is UnregisteredValue and value.path == target
    assert repr(value).startswith(f"<{target}>(command=")


def test_a_forged_value_nested_in_a_tuple_or_an_out_of_band_message_is_refused(marker):
    nested = msgpack.packb([1, msgpack.ExtType(2, forged("os:system", marker))])
    with pytest.raises(CodecError, match="'os:system'"):
        unpackb(nested)
    with pytest.raises(CodecError, match="'os:system'"):
        unpackb_out_of_band(nested, [])


def test_a_registered_value_type_with_foreign_fields_is_refused(marker):
    from tests.log.log_flows import Point

    data = msgpack.packb(msgpack.ExtType(EXT_DATACLASS, packb(["tests.log.log_flows:Point", {"x": 1.0, "evil": 2}])))
    with pytest.raises(CodecError, match="has no field"):
        unpackb(data)
    assert unpackb(packb(Point(1.0, 2.0))) == Point(1.0, 2.0)


def test_a_plain_dataclass_is_refused_when_encoding_with_the_fix():
    from dataclasses import dataclass

    @dataclass
    class Plain:
        x: int

    with pytest.raises(CodecError, match=r"a dataclass that is not a registered value type.*\n.*decorate the class "
                                         r"with @io"):
        packb({"a": Plain(1)})


# ---------------------------------------------------------------------------------------------
# The wire: a data message to a consumer's worker, a report to the coordinator
# ---------------------------------------------------------------------------------------------
def _data_message(value_bytes: bytes, producer: str = "camera", port: str = "frame") -> bytes:
    """A data message ``[envelope]`` whose envelope ``[2, tag, seq, frontier, producer, port,
    value]`` carries ``value_bytes`` as its value."""
    head = [WIRE_VERSION, [0, 1], 0, [0, 1], producer, port]
    envelope = b"\x97" + b"".join(msgpack.packb(x) for x in head) + value_bytes
    return msgpack.packb([envelope])


@pytest.mark.parametrize("target", TARGETS)
def test_a_data_message_carrying_a_forged_value_is_garbage(target, marker):
    with pytest.raises(WireError, match=rf"the value of a data message cannot be decoded: .*'{target}'"):
        decode_data(_data_message(forged(target, marker)), ("camera", "frame"))


def test_a_report_carrying_a_forged_event_is_garbage_when_its_events_are_decoded(marker):
    report = Report(node="camera", records=(), events=((1, _data_message(forged("os:system", marker))),)).encode()
    decoded = Report.decode(report, node="camera")
    with pytest.raises(WireError, match="'os:system'"):
        decode_data(decoded.events[0][1])


# ---------------------------------------------------------------------------------------------
# The hand-over state file: a restarting flow's old process writes it, its new one reads it
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("target", TARGETS)
def test_a_hand_over_state_holding_a_forged_value_is_refused(target, marker):
    state = b"\x81" + msgpack.packb("held") + b"\x91" + forged(target, marker)  # {"held": [value]}
    with pytest.raises(WireError, match=rf"^not Retriever codec data \(\w+Error: cannot decode a value of type "
                                        rf"'{target}': no value type of that name is registered"):
        decode_handover_state(state)


# ---------------------------------------------------------------------------------------------
# An IR file: `retriever ir X.json`, `retriever run X.json`
# ---------------------------------------------------------------------------------------------
def _forged_ir(tmp_path: Path, marker: Path) -> Path:
    doc = build_small().build_ir().doc
    counter = next(n for n in doc["nodes"] if n["id"] == "counter")
    counter["params"]["scale"] = {"$msgpack": base64.b64encode(forged("os:system", marker)).decode()}
    path = tmp_path / "forged.json"
    path.write_text(json.dumps(doc))
    return path


def test_an_ir_parameter_naming_a_callable_is_refused(tmp_path, marker):
    ir = _forged_ir(tmp_path, marker)
    result = cli("run", ir, "--duration", "0.2", pythonpath=ROOT)
    assert result.returncode != 0, result.stdout
    assert "error: " in result.stderr and "'os:system'" in result.stderr, result.stderr
    assert "Traceback" not in result.stderr
    assert not marker.exists()


def test_drawing_an_ir_never_decodes_its_parameters(tmp_path, marker):
    """`retriever ir X.json` reads and checks the IR and draws it: it imports nothing and decodes
    no parameter, so one naming a callable is shown as the text it is, and nothing runs."""
    ir = _forged_ir(tmp_path, marker)
    for fmt in ("json", "dot"):
        result = cli("ir", ir, "--format", fmt, pythonpath=ROOT)
        assert result.returncode == 0, result.stderr
        assert "counter" in result.stdout
    assert not marker.exists()


# ---------------------------------------------------------------------------------------------
# A log: read_log().trace(), `retriever log cat`, `retriever replay`
# ---------------------------------------------------------------------------------------------
WRITE_FORGED_LOG = """
import dataclasses, sys
from retriever import Pipeline, Rate, Trigger
from retriever.codec import register_value_type
from tests.log.log_flows import Echo, Emit

@dataclasses.dataclass
class Forged:
    command: str

Forged.__module__, Forged.__qualname__ = sys.argv[3], sys.argv[4]  # the attacker's own process
register_value_type(Forged)
with Pipeline("forged") as pipe:
    emit = Emit() @ Rate(hz=10)
    emit.values = [[Forged(command="touch " + sys.argv[2])]] * 3
    emit.then(Echo().configure(on_error="skip_tick") @ Trigger(), map={"value": "mix"})
pipe.run(duration=0.3, log=sys.argv[1])
"""


@pytest.fixture
def forged_log(tmp_path: Path, marker: Path) -> Path:
    path = tmp_path / "forged.mcap"
    subprocess.run([sys.executable, "-c", textwrap.dedent(WRITE_FORGED_LOG), str(path), str(marker), "os", "system"],
                   check=True, cwd=ROOT, env={**cli_env(), "PYTHONPATH": str(ROOT)}, timeout=120)
    return path


def test_reading_a_forged_log_s_values_is_refused(forged_log, marker):
    with pytest.raises(LogError, match=r"cannot decode event emit\.value #0: cannot decode a value of type 'os:system'"):
        read_log(forged_log).trace()


def test_log_cat_shows_a_forged_value_inert(forged_log, marker):
    result = cli("log", "cat", forged_log, "--node", "emit", pythonpath=ROOT)
    assert result.returncode == 0, result.stderr
    assert f"<os:system>(command='touch {marker}')" in result.stdout


def test_replaying_a_forged_log_is_refused(forged_log, marker):
    result = cli("replay", forged_log, pythonpath=ROOT)
    assert result.returncode != 0
    assert "error: " in result.stderr and "'os:system'" in result.stderr, result.stderr
