"""A worker's command line: one builder for every host, one reader of the start mode."""

from __future__ import annotations

import sys

import pytest

from retriever.backends.zenoh.command import (
    FIRST,
    FRESH,
    JOIN,
    WORKER_MODULE,
    Mode,
    mode_args,
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
    assert parse_mode(mode_args((1_000, 2_000))) == Mode(JOIN, 1_000, 2_000)
    assert parse_mode(mode_args((1_000, 2_000), fresh=True)) == Mode(FRESH, 1_000, 2_000)


@pytest.mark.parametrize("args", [["--join", "1; rm -rf /", "2"], ["--fresh", "-5", "-1"], ["--join", "²", "1"],
                                  ["--join", "0", "1" + "0" * 26], ["--evil", "1", "2"], ["--join", "1"], "--join"])
def test_a_mode_that_is_not_one_is_refused(args):
    with pytest.raises(ValueError, match=r"is not \[\] nor \[--join\|--fresh, T0, END\]"):
        parse_mode(args)
