"""Flows deployed on worker daemons in the netns lab (test_deploy.py): importable by a worker
from its ``--path`` (this folder) as the module ``deploy_flows``, which is how the coordinator
loads this file too (``retriever deploy tests/deploy/deploy_flows.py:pipe``)."""

from __future__ import annotations

from dataclasses import dataclass

from retriever import Flow, Latest, Pipeline, Rate, Trigger, io


@io
@dataclass
class Count:
    n: int


class Counter(Flow[None, Count]):
    """A source: 1, 2, 3, …"""

    def __init__(self):
        self.k = 0

    def reset(self) -> None:
        self.k = 0

    def step(self, inp: None) -> Count:
        self.k += 1
        return Count(n=self.k)


class Relay(Flow[Count, Count]):
    """Passes the count on."""

    def step(self, inp: Count) -> Count:
        return Count(n=inp.n)


with Pipeline("lab") as pipe:
    counter = Counter().configure(name="counter") @ Rate(hz=20)
    relay = Relay().configure(name="relay") @ Trigger()
    sink = Relay().configure(name="sink") @ Trigger()
    counter.then(relay, sync=Latest()).then(sink, sync=Latest())


with Pipeline("lab-watch") as watched:
    # a consumer on a clock of its own: a tick whose input is not complete by its deadline is skipped
    source = Counter().configure(name="counter") @ Rate(hz=20)
    watcher = Relay().configure(name="watcher") @ Rate(hz=20)
    source.then(watcher, sync=Latest())
