"""The MCAP event log: the system of record of a run (docs/log.md).

    pipe.run(duration=10, log="run.mcap")      # write
    log = read_log("run.mcap")                 # read: log.ir, log.run, log.trace(), ...
    replay(log).identical                      # re-execute every non-source step, compare bytes
    resim(log).identical                       # re-run the graph from the logged sources
    recover("killed.mcap")                     # salvage a log whose writer was killed
    export_dataset(["run.mcap"], "ds", flow="policy", format="lerobot")   # a training set (docs/learning.md)
"""

from .dataset import ExportSummary, export_dataset
from .reader import LoggedEvent, RunLog, read_log
from .recover import Recovered, recover
from .replay import Divergence, ReplayReport, ResimReport, replay, resim
from .writer import LogWriter

__all__ = ["Divergence", "ExportSummary", "LogWriter", "LoggedEvent", "Recovered", "ReplayReport", "ResimReport",
           "RunLog", "export_dataset", "read_log", "recover", "replay", "resim"]
