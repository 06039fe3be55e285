"""The live views of a running pipeline (``pipe.run(..., foxglove=PORT, rerun=TARGET)``), fed
by the coordinator with what the workers' reports bring, never on the flows' path.

Every view takes the same three calls (:class:`RunView`); :class:`LiveViews` feeds each of them.
A view is not the run: one that fails is stopped with a warning, and the run and the other views
go on.
"""

from __future__ import annotations

import os
import warnings
from typing import Any, Callable, Protocol

from ..errors import RetrieverWarning


class RunView(Protocol):
    """What a live view is told of a run (log/foxglove.py's LiveView, log/rerun_live.py's)."""

    #: what the view is called in its warning ("the Foxglove live view")
    title: str

    def event(self, node: str, port: str, tag: tuple[int, int], seq: int, value: Any, wall_ns: int) -> None:
        """An event of ``node.port`` at ``tag``, published at ``wall_ns`` (Unix ns; 0: unknown);
        ``value`` is NOT_KEPT when the run does not bring values to the coordinator."""

    def step(self, node: str, tag: tuple[int, int], consumed: dict, produced, status: str, detail,
             start_ns: int, wall_ns: int) -> None:
        """A step record: its tick, events consumed and produced, status, detail, when its step
        began (Unix ns) and how long it took."""

    def close(self) -> None:
        """The run is over: what the view holds is sent, and its sink closed."""


class LiveViews:
    """The run's live views, each told every event and step record in turn."""

    def __init__(self, views: list[RunView]):
        self.views = list(views)
        #: why a view stopped, by its title
        self.errors: dict[str, str] = {}

    def add(self, view: RunView) -> RunView:
        self.views.append(view)
        return view

    def _each(self, method: str, *args) -> None:
        for view in list(self.views):
            try:
                getattr(view, method)(*args)
            except Exception as e:  # noqa: BLE001 - the view is not the run: it stops, the run goes on
                self.views.remove(view)
                self.errors[view.title] = f"{type(e).__name__}: {e}"
                warnings.warn(f"{view.title} stopped: {self.errors[view.title]}", RetrieverWarning, stacklevel=3)
                if method != "close":
                    self._close_quietly(view)

    @staticmethod
    def _close_quietly(view: RunView) -> None:
        try:
            view.close()
        except Exception:  # noqa: BLE001 - it failed already, and said so
            pass

    def event(self, node: str, port: str, tag, seq: int, value: Any, wall_ns: int) -> None:
        self._each("event", node, port, tag, seq, value, wall_ns)

    def step(self, node: str, tag, consumed, produced, status: str, detail, start_ns: int, wall_ns: int) -> None:
        self._each("step", node, tag, consumed, produced, status, detail, start_ns, wall_ns)

    def close(self) -> None:
        self._each("close")
        self.views.clear()


def open_live_views(ir, *, foxglove: int | None, rerun: str | os.PathLike | None,
                    say: Callable[[str], None]) -> LiveViews | None:
    """The views asked for (a Foxglove server on port ``foxglove``, a Rerun stream to ``rerun``),
    each said with ``say`` once it is up; None if none was. One that cannot start is an error,
    and the ones started before it are closed."""
    if foxglove is None and rerun is None:
        return None
    views = LiveViews([])
    try:
        if foxglove is not None:
            from .foxglove import LiveView

            server = views.add(LiveView(foxglove, ir))
            say(f"Foxglove live view on ws://127.0.0.1:{server.port} (in the Foxglove app: Open connection, "
                "Foxglove WebSocket)")
        if rerun is not None:
            from .rerun_live import RerunLiveView

            views.add(RerunLiveView(rerun, ir.name))
            say(f"Rerun live view streaming to {rerun}")
    except BaseException:
        views.close()
        raise
    return views
