"""Retriever: closed-loop robot agents with explicit time.

Flows (``step``) on clocks (``Rate``, ``Trigger``, ``Hybrid``), edges with sync policies
(``Latest``, ``Window``, ``ActionChunking``, …), compiled to an IR and run by a backend.
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
from .log import read_log
from .pipeline import Pipeline
from .sync import MISSING, ActionChunking, Exact, Latest, LatestDistinct, Queue, SyncPolicy, Window
from .trace import NOT_KEPT, Event, StepRecord, Trace

__all__ = sorted([
    "IR", "MISSING", "NOT_KEPT", "ActionChunking", "BackendError", "Burst", "CausalityError", "Clock", "ClockError",
    "CodecError", "Event", "EventStream", "Exact", "Flow", "GraphError", "Hybrid", "IRError",
    "InternalError", "Latest", "LatestDistinct", "LogError", "LogWriteError", "Pipeline", "PlacementError",
    "Queue", "Rate", "RestartLimitError", "RetrieverError", "RetrieverWarning", "SetupError", "StarvedFlowWarning", "StepError", "StepRecord",
    "SyncPolicy", "Trace", "Trigger", "UnregisteredTypeError", "ValuesNotKeptError", "Window", "available_backends", "flow_io", "init", "io",
    "read_log",
])
