"""The prior of a per-condition identification in the served modes (``identification.mode`` ``combined``;
docs/design/identification.md, "The prior of a served fit"): the cold physics prior at the condition
(``model.identify_prior.condition_prior``, σ(ln H) = ln 3) plus, once a speed map exists, the map's data
information at the condition's speed (``model.identify_prior.with_map``, weighed by the map's covariance
intersection weight). The paper's protocol (``per_condition``) takes none: the unregularised fit.

Pure numpy (``model`` only): the core builds one per job and sends it in the ``JobRequest``.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from model.hmap import Gaussian
from model.identify_prior import COLD_SD_LOG, HPrior, condition_prior, with_map
from service.identify.speedmap import SpeedMap

__all__ = ["ServedMapPrior", "job_prior", "log_h_marginal"]


def log_h_marginal(family: Any, mean: Any, cov: Any, speed_rpm: float, ambient_c: float) -> tuple[Any, Any]:
    """ln H (7,) and its covariance (7, 7) of a map θ ~ N(``mean``, ``cov``) at one speed [rpm] and ambient
    [°C] (linear: the tabulated family's ln H is linear in θ; the physics family's linearised)."""
    mu = family.log_h(mean, [abs(speed_rpm)], ambient_c)[0]
    jac = family.log_h_jacobian(mean, [abs(speed_rpm)], ambient_c)[0]  # (7, p)
    cov7 = jac @ np.asarray(cov) @ jac.T
    return np.asarray(mu), 0.5 * (cov7 + cov7.T)


def job_prior(
    spec: Any,
    box: tuple[float, float],
    speed_rpm: float,
    ambient_c: float,
    *,
    speed_map: SpeedMap | None,
    map_cold: Gaussian | None,
    weight: float,
) -> HPrior:
    """The prior of a per-condition job at ``speed_rpm`` and ``ambient_c``: the cold physics prior, plus the
    map's data information there when ``speed_map`` (and the map's own cold prior ``map_cold``) exist."""
    cold = condition_prior(spec, speed_rpm, box=box)
    if speed_map is None or map_cold is None:
        return cold
    fam = speed_map.model_family
    mu, cov = log_h_marginal(fam, speed_map.mean, speed_map.cov, speed_rpm, ambient_c)
    mu0, cov0 = log_h_marginal(fam, map_cold.mean, map_cold.cov, speed_rpm, ambient_c)
    fitted = speed_map.fitted_at.strftime("%H:%M:%SZ")
    return with_map(
        cold,
        post_mean=mu,
        post_cov=cov,
        map_cold_mean=mu0,
        map_cold_cov=cov0,
        weight=weight,
        source=f"physics curves σ(ln H) {COLD_SD_LOG:.2f} + speed map to {fitted} ×{weight:g}",
    )


class ServedMapPrior:
    """What ``/chtc`` serves from a speed map at one speed (``service.serve.views.map_record``), per H: the
    map's own value and band where its σ(ln H) there is at most the cold prior's (ln 3; the speeds the data
    visited: exactly the map's answer); elsewhere the map's information there on the cold physics prior
    (``job_prior`` with weight 1: no window shares the map's data here). The map's own cold prior is σ
    1.5–2.3 in ln H with its trend term: 95 % bounds up to 100× the box at a speed never visited. Keeps each
    map family's cold prior (a 56 × 56 inverse), and the last answer: every ``/chtc`` until the next sample
    asks for the same map, speed and ambient (~0.9 ms each otherwise: py-spy, ×60 demo, loaded machine)."""

    def __init__(self, spec: Any, box: tuple[float, float]) -> None:
        self.spec = spec
        self.box = (float(box[0]), float(box[1]))
        self._cold: dict[tuple[str, float], Gaussian] = {}
        self._last: tuple[SpeedMap, tuple[float, float, float], HPrior] | None = None

    def at(self, speed_map: SpeedMap, *, level_sd: float, speed_rpm: float, ambient_c: float) -> HPrior:
        """ln H (7,) and its covariance served at ``speed_rpm`` [rpm] and ``ambient_c`` [°C], as an ``HPrior``
        whose ``reference_var`` is the cold prior's (``dominated`` then flags the H no data saw)."""
        args = (float(level_sd), float(speed_rpm), float(ambient_c))
        last = self._last  # one read: API threads may call this at once (the swap below is atomic)
        if last is not None and last[0] is speed_map and last[1] == args:
            return last[2]
        prior = self._compute(speed_map, level_sd=args[0], speed_rpm=args[1], ambient_c=args[2])
        self._last = (speed_map, args, prior)
        return prior

    def _compute(self, speed_map: SpeedMap, *, level_sd: float, speed_rpm: float, ambient_c: float) -> HPrior:
        key = (speed_map.family, float(level_sd))
        cold = self._cold.get(key)
        if cold is None:
            cold = self._cold[key] = speed_map.model_family.prior(self.spec, level_sd=float(level_sd))
        mu, cov = log_h_marginal(speed_map.model_family, speed_map.mean, speed_map.cov, speed_rpm, ambient_c)
        wide = np.diag(cov) > COLD_SD_LOG**2
        # prior_dominated against the prior each H's answer rests on: the map's own cold prior there, or ln 3
        _, cold_cov = log_h_marginal(speed_map.model_family, cold.mean, cold.cov, speed_rpm, ambient_c)
        ref = np.where(wide, COLD_SD_LOG**2, np.diag(cold_cov))
        source = "speed map"
        if wide.any():
            fused = job_prior(
                self.spec,
                self.box,
                speed_rpm,
                ambient_c,
                speed_map=speed_map,
                map_cold=cold,
                weight=1.0,
            )
            keep = ~wide
            mu = np.where(wide, fused.log_mean, mu)
            cov = np.where(np.outer(keep, keep), cov, 0.0) + np.diag(
                np.where(wide, np.diag(fused.log_cov), 0.0)
            )
            source = (
                "speed map; " + ", ".join(f"H{i + 1}" for i in np.flatnonzero(wide)) + " on the cold prior"
            )
        return HPrior(mu, cov, ref, source=source)
