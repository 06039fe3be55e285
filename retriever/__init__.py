"""Retriever: closed-loop robot agents with explicit time.

Flows (``step``) on clocks (``Rate``, ``Trigger``, ``Hybrid``), edges with sync policies
(``Latest``, ``Window``, ``ActionChunking``, …), compiled to an IR and run by a backend.

Layers, lowest first: a module imports from its own layer and those below, never from one above
(not lazily inside a function, not under ``if TYPE_CHECKING:``); ``<`` separates layers, spaces
the modules of one layer, and a package stands for its modules (tests/test_layers.py checks it).

    kernel     time < errors < codec code < clocks < sync < trace < declaring < flow < ir < graph < rebuild features < plan tick
    placement  placement
    log        log
    backends   backends.base < starved < backends.inproc_ticks backends.inproc_compiled backends.inproc < backends.zenoh < backends.dora < backends
    pipeline   pipeline
    run        loading
    replay     replay
    libraries  gym learn ros2
    cli        cli __main__

The kernel ends in what every backend shares: ``plan``, a graph's wiring node by node, computed
once (plain data, which a worker gets or makes from the IR); ``tick``, the reference tick (input
selection, the step call, the one ``on_error`` decision), which every backend runs or is held to.

This package's own names (below) re-export the curated API from every layer. ``agents/`` sits
above everything and nothing in ``retriever/`` imports it. One alias is kept for the spelling
the paper uses, resolved on first use: ``retriever.flow.Pipeline``.
"""

from .backends import available_backends, init
from .clocks import Clock, Hybrid, Rate, Trigger
from .errors import (
    BackendError,
    CausalityError,
    ClockError,
    CodecError,
    GraphError,
    InternalError,
    IRError,
    LogError,
    LogWriteError,
    PlacementError,
    RestartLimitError,
    RetrieverError,
    RetrieverWarning,
    SetupError,
    StarvedFlowWarning,
    StepError,
    UnregisteredTypeError,
    ValuesNotKeptError,
)
from .flow import Burst, EventStream, Flow, flow_io, io
from .ir import IR
from .log import RunEnd, read_log
from .pipeline import Pipeline
from .sync import MISSING, ActionChunking, Exact, Latest, LatestDistinct, Queue, SyncPolicy, Window
from .trace import NOT_KEPT, Event, StepRecord, StepStatus, Trace

__all__ = sorted([
    "IR", "MISSING", "NOT_KEPT", "ActionChunking", "BackendError", "Burst", "CausalityError", "Clock", "ClockError",
    "CodecError", "Event", "EventStream", "Exact", "Flow", "GraphError", "Hybrid", "IRError",
    "InternalError", "Latest", "LatestDistinct", "LogError", "LogWriteError", "Pipeline", "PlacementError",
    "Queue", "Rate", "RestartLimitError", "RetrieverError", "RetrieverWarning", "RunEnd", "SetupError", "StarvedFlowWarning", "StepError", "StepRecord",
    "StepStatus", "SyncPolicy", "Trace", "Trigger", "UnregisteredTypeError", "ValuesNotKeptError", "Window", "available_backends", "flow_io", "init", "io",
    "read_log",
])
