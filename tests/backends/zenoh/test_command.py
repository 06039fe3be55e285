"""A worker's command line: one builder for every host, one reader of it and of the start mode."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from retriever.backends.zenoh.command import (
    DORA_NODE_MODULE,
    FIRST,
    FRESH,
    GROUP_MODULE,
    JOIN,
    WORKER_MODULE,
    Command,
    StartMode,
    mode_args,
    parse_command,
    parse_mode,
    worker_command,
)


def test_the_command_runs_the_worker_module_with_the_spec_node_and_mode():
    assert worker_command("/run/spec.json", "camera") == [sys.executable, "-m", WORKER_MODULE, "/run/spec.json",
                                                          "camera"]
    assert worker_command("/run/spec.json", "camera", mode_args((5, 9), fresh=True), python="/py") == [
        "/py", "-m", WORKER_MODULE, "/run/spec.json", "camera", FRESH, "5", "9"]


def test_a_mode_reads_back_as_it_was_built():
    assert parse_mode(mode_args(None)) == FIRST
    assert parse_mode(mode_args((1_000, 2_000))) == StartMode(JOIN, 1_000, 2_000)
    assert parse_mode(mode_args((1_000, 2_000), fresh=True)) == StartMode(FRESH, 1_000, 2_000)


@pytest.mark.parametrize("args", [["--join", "1; rm -rf /", "2"], ["--fresh", "-5", "-1"], ["--join", "²", "1"],
                                  ["--join", "0", "1" + "0" * 26], ["--evil", "1", "2"], ["--join", "1"], "--join"])
def test_a_mode_that_is_not_one_is_refused(args):
    with pytest.raises(ValueError, match=r"is not \[\] nor \[--join\|--fresh, T0, END\]"):
        parse_mode(args)


@pytest.mark.parametrize("module", [WORKER_MODULE, GROUP_MODULE, DORA_NODE_MODULE])
def test_a_command_line_reads_back_as_it_was_built(module):
    mode = mode_args((5, 9), fresh=True) if module != DORA_NODE_MODULE else []
    _, _, built, *argv = worker_command("/run/spec.json", "camera", mode, module=module)
    assert built == module
    assert parse_command(argv, module) == Command(Path("/run/spec.json"), "camera", parse_mode(mode))


@pytest.mark.parametrize(("module", "argv", "wrong"), [
    (WORKER_MODULE, [], "no SPEC.json"),
    (WORKER_MODULE, ["/run/spec.json"], "no NODE"),
    (GROUP_MODULE, ["/run/spec.json"], "no NAME"),
    (WORKER_MODULE, ["/run/spec.json", "camera", "--join", "1"], r"mode \['--join', '1'\] is not \[\] nor"),
    (WORKER_MODULE, ["/run/spec.json", "camera", "--evil", "1", "2"], r"mode \[.--evil., .1., .2.\] is not"),
    (DORA_NODE_MODULE, ["/run/spec.json"], "no DORA_ID"),
    (DORA_NODE_MODULE, ["/run/spec.json", "camera", "--join", "1", "2"], "unexpected argument"),
])
def test_a_command_line_that_is_not_one_is_refused_with_the_usage_line(module, argv, wrong):
    takes_mode = module != DORA_NODE_MODULE
    usage = f"usage: python -m {module} SPEC.json \\S+" + (r" \[--join\|--fresh T0 END\]" if takes_mode else "")
    with pytest.raises(ValueError, match=f"^{usage}: {wrong}"):
        parse_command(argv, module)
