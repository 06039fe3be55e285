"""The MCAP event log: the system of record of a run (docs/log.md).

    pipe.run(duration=10, log="run.mcap")      # write
    log = read_log("run.mcap")                 # read: log.ir, log.run, log.trace(), ...
    replay(log).identical                      # re-execute every non-source step, compare bytes
    resim(log).identical                       # re-run the graph from the logged sources
    recover("killed.mcap")                     # salvage a log whose writer was killed
    export_dataset(["run.mcap"], "ds", flow="policy", format="lerobot")   # a training set (docs/learning.md)

Replaying runs a pipeline, a layer above this package (``retriever/__init__.py`` draws the
layers): ``replay``, ``resim`` and their reports live in ``retriever.replay`` and are found here
on first use, so that ``from retriever.log import replay`` keeps working.
"""

from .dataset import ExportSummary, export_dataset
from .reader import LoggedEvent, RunLog, read_log
from .recover import Recovered, recover
from .writer import LogWriter

_REPLAY_NAMES = frozenset({"Divergence", "ReplayReport", "ResimReport", "replay", "resim"})


def __getattr__(name: str):
    if name in _REPLAY_NAMES:  # imported on first use: retriever.replay imports this package
        from .. import replay as replay_module

        return getattr(replay_module, name)
    raise AttributeError(f"module 'retriever.log' has no attribute {name!r}")


__all__ = ["Divergence", "ExportSummary", "LogWriter", "LoggedEvent", "Recovered", "ReplayReport", "ResimReport",
           "RunLog", "export_dataset", "read_log", "recover", "replay", "resim"]
