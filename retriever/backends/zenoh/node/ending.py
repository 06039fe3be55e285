"""How a node loop ends before the run's end: one value (``NodeLoop.ending``, set only through
``NodeLoop.stop``), which its process reads to know what to do once the loop is out of its run."""

from __future__ import annotations

import enum


class Ending(enum.IntEnum):
    """Why a node loop left its run early. The greater, the graver: when two came, the graver
    is the loop's ending (``NodeLoop.ending`` says why)."""

    #: a ``stop`` (the run's control, or SIGTERM) or a step's ``sys.exit(0)``: the loop finishes
    #: (what it holds released, nothing more promised) and its process says ``done``, stopped
    TOLD_TO_STOP = 1
    #: the coordinator's ``handover`` to a restarting flow: the loop does not finish; its process
    #: writes the loop's state for the flow's new process (handover.py)
    HANDING_OVER = 2
    #: the coordinator counts the process lost, or its parent died: the loop does not finish and
    #: its process ends without a word, as if killed
    ABANDONED = 3
