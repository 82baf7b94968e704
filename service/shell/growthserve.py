"""The engine's side of the served thermal growth (``GET /compensation``; docs/design/growth.md, "Serving"):
when the condition terms are computed, and the growth history of an offline run. What is served and how is
``service.serve.compensation.GrowthServer`` (over ``service.estimate``); the terms' cache is
``service.estimate.growthterms.TermsCache``.

- :class:`TermsRefresher`: the shell hands it each published view; when the view has a new key
  (``GrowthServer.wants_refresh``) its condition terms are computed in a thread (~0.25 s), one refresh at a
  time, for the newest view wanting one, never on the event loop;
- :class:`GrowthHistory`: ``run_offline``'s ``on_sample`` hook for ``chtc identify --json``'s growth history.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import logging
from collections.abc import Callable, Coroutine
from typing import TYPE_CHECKING, Protocol

from service.contracts.errors import NotReadyError
from service.contracts.growth import GrowthEstimate
from service.serve.compensation import GrowthServer
from service.serve.view import CoreView

if TYPE_CHECKING:
    from service.modelload import LoadedModel

__all__ = ["GrowthHistory", "TermsRefresher"]

log = logging.getLogger(__name__)


class TermsRefresher:
    """New identification or condition: the growth's condition terms in a thread (with a running loop;
    without, the first ``compensation()`` computes them in its caller's thread). Keys that change while a
    refresh runs (a condition change, then the live H at its speed, then an identification) coalesce into one
    refresh of the newest view. Event-loop thread only (``spawn`` runs a coroutine as the shell's task)."""

    def __init__(
        self, growth: GrowthServer, spawn: Callable[[Coroutine[object, object, None]], object]
    ) -> None:
        self.growth = growth
        self._spawn = spawn
        self._view: CoreView | None = None  # the newest view whose growth terms are wanted
        self._task: asyncio.Future[None] | None = None

    def want(self, view: CoreView) -> None:
        """``view`` wants its terms (``GrowthServer.wants_refresh`` said so): one refresh at a time."""
        self._view = view
        if self._task is None or self._task.done():
            task = self._spawn(self._run())
            self._task = task if isinstance(task, asyncio.Future) else None

    async def _run(self) -> None:
        while (view := self._view) is not None:
            self._view = None
            try:
                await asyncio.to_thread(self.growth.refresh, view)
            except Exception as err:  # a request retries it and raises to its caller; say it here too
                log.warning("growth terms failed: %s: %s", type(err).__name__, err)


class GrowthHistory:
    """The growth at each identification's end, offline (``run_offline``'s ``on_sample`` hook): after the
    sample whose identification succeeded (the live state then holds the filtered field), and the growth
    of that field is what ``/compensation`` would have served then (the same ``GrowthServer``, the same
    reference: ``t_ref_c``, by default the provisional zero, the first converged live field's). ``by_id``:
    identification id -> ``GrowthEstimate``; in combined mode an identification that does not serve (a map
    fit while the held condition's per-condition one does) gets the growth served then, the serving one's."""

    def __init__(self, model: LoadedModel, *, t_ref_c: float | None = None) -> None:
        self.model = model
        self.t_ref_c = t_ref_c
        self.by_id: dict[int, GrowthEstimate] = {}
        self._server: GrowthServer | None = None
        self._last_id = 0  # the newest identification id handled

    def __call__(self, core: ServiceCoreLike, k: int, last_ok: object) -> None:
        view = core.view()
        if self._server is None:
            self._server = GrowthServer(self.model, t_ref_c=self.t_ref_c)
            with contextlib.suppress(NotReadyError):  # built now: the provisional zero is the first converged
                self._server.prepare()  # live field's, as in the service (no mechanics: no growth at all)
        self._server.observe(view)
        rec = view.current
        if rec is None or view.current_from_restore:
            return
        # the identifications that succeeded since the last call (ids grow; newest first): each gets the
        # growth served now, the current one's (combined mode: a map fit at a held condition is not current)
        new = list(itertools.takewhile(lambda r: r.id > self._last_id, view.records))
        ok = [r.id for r in new if r.outcome == "ok" and r.id not in self.by_id]
        if not ok:
            return
        est = self._server.estimate(view)
        if est is not None:
            self._last_id = max(self._last_id, new[0].id)
            self.by_id.update(dict.fromkeys(ok, est))


class ServiceCoreLike(Protocol):
    """What ``GrowthHistory`` reads of ``service.core.machine.ServiceCore``."""

    def view(self) -> CoreView: ...
