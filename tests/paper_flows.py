"""Flows written as the seed paper writes them (Appendix F, Listing 4): ``flow_io``, a ``run``
method instead of ``step``, ``super().__init__()``; importable, so a worker process rebuilds them."""

from __future__ import annotations

from dataclasses import dataclass

import sys

import numpy as np

from retriever.flow import Flow, Latest, Pipeline, Rate, Trigger, flow_io


@flow_io
@dataclass
class RandomSequence:
    data: np.ndarray


class SourceFlow(Flow[None, RandomSequence]):
    def __init__(self):
        super().__init__()
        self.i = 0

    def run(self, _):
        self.i += 1
        return RandomSequence(data=np.full(4, self.i, dtype=np.uint64))


class SinkFlow(Flow[RandomSequence, None]):
    def __init__(self):
        super().__init__()
        self.seen = []

    def run(self, input: RandomSequence):
        self.seen.append(int(input.data[0]))


def build() -> Pipeline:
    pipe = Pipeline("paper_spellings")
    with pipe:
        source = SourceFlow() @ Rate(hz=20)
        sink = SinkFlow() @ Trigger("data")
        pipe.connect(source, sink, sync=Latest())
    return pipe


class EndingSource(Flow[None, RandomSequence]):
    """Ends the whole run from its step, as the paper's benchmark does: ``sys.exit(code)`` at
    its ``at``-th step."""

    def __init__(self, at: int, code: int = 0, size: int = 4):
        super().__init__()
        self.at, self.code, self.size, self.i = at, code, size, 0

    def run(self, _):
        self.i += 1
        if self.i == self.at:
            print("Benchmarking data collection complete!")
            sys.exit(self.code)
        return RandomSequence(data=np.full(self.size, self.i, dtype=np.uint64))


def build_ending(at: int, code: int = 0, size: int = 4, deadline: float | None = None) -> Pipeline:
    pipe = Pipeline("ending") if deadline is None else Pipeline("ending", deadline=deadline)
    with pipe:
        source = EndingSource(at, code, size).configure(name="source") @ Rate(hz=20)
        sink = SinkFlow().configure(name="sink") @ Trigger("data")
        pipe.connect(source, sink, sync=Latest())
    return pipe
