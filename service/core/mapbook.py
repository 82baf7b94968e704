"""The core's speed-map bookkeeping (modes ``speed_map`` and ``combined``, docs/design/hmap.md): when a map
fit is due, the running fit, the posteriors kept for the next windows' priors and the visited-speed tally.
Pure: no I/O, no clock; the core's map track (``service.core.maptrack.MapTrack``) owns one.
"""

from __future__ import annotations

from datetime import UTC, datetime

import numpy as np

from model.hmap import Family, Gaussian
from model.hmap_identify import forget
from service.core.config import CoreConfig
from service.identify.speedmap import SpeedMap, VisitTally
from service.modelload import LoadedModel


class MapBook:
    """The core's speed-map bookkeeping: trigger times, the running fit, the posteriors kept for the
    next windows' priors, the visited-speed tally."""

    KEPT = 64  # posteriors kept (a fit every few minutes: > 1 h of them)

    def __init__(self, config: CoreConfig, model: LoadedModel, restored: SpeedMap | None) -> None:
        cfg = config.speed_map
        self.cfg = cfg
        self.family = Family(cfg.family)
        self.cold = self.family.prior(model.spec, level_sd=cfg.prior_level_sd)
        self.tally = VisitTally(bin_rpm=cfg.bin_rpm, tau_h=cfg.tau_h)
        self.changed_at: float | None = None  # last confirmed condition change not fitted since
        self.retry_after: float | None = None
        self.running: int | None = None
        self.live_key: tuple[object, ...] | None = None
        self._launched: tuple[float, int, tuple[np.ndarray, np.ndarray]] | None = None
        self._last_end: float | None = None
        # (window end epoch s, posterior), oldest first
        self._posteriors: list[tuple[float, Gaussian]] = []
        if restored is not None:
            t = restored.fitted_at.timestamp()
            self._posteriors.append((t, Gaussian(np.array(restored.mean), np.array(restored.cov))))
            self.tally.restore(restored.visited_rpm, restored.visited_s, t)

    def due(self, ts: float) -> str | None:
        """Why a fit is due now (None: not due or one is running): a debounced condition change, the first
        fit, or ``refit_s`` since the last window's end."""
        if self.running is not None or (self.retry_after is not None and ts < self.retry_after):
            return None
        if self.changed_at is not None and ts - self.changed_at >= self.cfg.debounce_s:
            return "condition-change"
        if self._last_end is None:
            return "first"
        if ts - self._last_end >= self.cfg.refit_s:
            return "scheduled"
        return None

    def prior_for(self, t_from: float, t_to: float) -> tuple[Gaussian, str]:
        """The prior of a window [t_from, t_to]: the newest posterior whose window ended by ``t_from``
        (no datum counted twice), its information decayed over the time to ``t_to`` (``forget``); the
        family's cold-start prior when there is none."""
        older = [(t, g) for t, g in self._posteriors if t <= t_from + 1e-6]
        if not older:
            return self.cold, "cold prior"
        t, g = older[-1]
        hours = max(0.0, t_to - t) / 3600.0
        source = f"fit to {datetime.fromtimestamp(t, tz=UTC):%H:%M:%S}"
        return forget(g, self.cold, elapsed_h=hours, tau_h=self.cfg.tau_h), source

    def current_theta(self, m: SpeedMap | None) -> tuple[np.ndarray, np.ndarray]:
        if m is None:
            return self.cold.mean, self.cold.cov
        return np.asarray(m.mean), np.asarray(m.cov)

    def live_theta(self, ts: float, m: SpeedMap | None) -> tuple[np.ndarray, np.ndarray, object]:
        """θ's mean and covariance whose H and band the live filter uses at ``ts`` (its H and considered H
        error: the newest map's), and a key that changes when they do. (Taking the covariance from the prior
        a window starting at ``ts`` would get instead was measured without effect and removed, issue 25;
        docs/design/hmap.md.)"""
        mean, cov = self.current_theta(m)
        return mean, cov, id(m)

    def launched(self, job_id: int, *, t_end: float, mask_used: int) -> None:
        self.running = job_id
        self._launched = (t_end, mask_used, self.tally.visited())
        self._last_end = t_end
        self.retry_after = None

    def finished(self) -> tuple[float, int, tuple[np.ndarray, np.ndarray]]:
        """The running fit's window end, channels used and the tally at its window end."""
        assert self._launched is not None
        out, self._launched, self.running = self._launched, None, None
        return out

    def intersect(self, prior: Gaussian, start_cov: np.ndarray) -> tuple[Gaussian, np.ndarray]:
        """Covariance intersection of the fit's prior and its start field (``prior_weight`` ω): a chained
        prior (an earlier window's posterior) and the live state at the window start were both made from
        earlier data, so their errors are correlated by an unknown amount; dividing the prior's covariance
        by ω and the start covariance by 1 − ω keeps the fused estimate consistent for any correlation
        (Julier & Uhlmann 1997). Unchanged for ω = 1 (treated as independent) and for the cold-start prior
        (the spindle file's: it shares no data with the start field)."""
        w = float(self.cfg.prior_weight)
        if w >= 1.0 or prior is self.cold:
            return prior, start_cov
        return Gaussian(prior.mean, prior.cov / w), np.asarray(start_cov) / (1.0 - w)

    def keep(self, t_end: float, posterior: Gaussian) -> None:
        self._posteriors = [*self._posteriors, (t_end, posterior)][-self.KEPT :]
