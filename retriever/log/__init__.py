"""The MCAP event log: the system of record of a run (docs/log.md).

    pipe.run(duration=10, log="run.mcap")      # write
    log = read_log("run.mcap")                 # read: log.ir, log.run, log.trace(), ...
    recover("killed.mcap")                     # salvage a log whose writer was killed
    export_dataset(["run.mcap"], "ds", flow="policy", format="lerobot")   # a training set (docs/learning.md)

Replaying a log runs a pipeline, a layer above this package (``retriever/__init__.py`` draws the
layers), so ``replay``, ``resim`` and their reports are ``retriever.replay``'s:
``from retriever.replay import replay, resim``.
"""

from .dataset import ExportSummary, export_dataset
from .format import RunEnd
from .reader import LoggedEvent, RunLog, read_log
from .recover import Recovered, recover
from .writer import LogWriter

__all__ = ["ExportSummary", "LogWriter", "LoggedEvent", "Recovered", "RunEnd", "RunLog", "export_dataset", "read_log",
           "recover"]
