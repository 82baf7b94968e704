"""The prior of a per-condition identification in the served modes (``experimental.mode`` ``combined``;
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
    """What ``/chtc`` serves from a speed map at one speed (``service.serve.views.map_record``): the same
    fusion with weight 1 (no window shares the map's data here), the cold physics prior in place of the map's
    own wider one (σ 1.5–2.3 in ln H with its trend term: 95 % bounds up to 100× the box at a speed the data
    never visited). At visited speeds the map's data dominate and nothing changes; elsewhere the band is the
    cold prior's, flagged ``prior_dominated``. Keeps each map family's cold prior (a 56 × 56 inverse)."""

    def __init__(self, spec: Any, box: tuple[float, float]) -> None:
        self.spec = spec
        self.box = (float(box[0]), float(box[1]))
        self._cold: dict[tuple[str, float], Gaussian] = {}

    def at(self, speed_map: SpeedMap, *, level_sd: float, speed_rpm: float, ambient_c: float) -> HPrior:
        key = (speed_map.family, float(level_sd))
        cold = self._cold.get(key)
        if cold is None:
            cold = self._cold[key] = speed_map.model_family.prior(self.spec, level_sd=float(level_sd))
        return job_prior(
            self.spec,
            self.box,
            speed_rpm,
            ambient_c,
            speed_map=speed_map,
            map_cold=cold,
            weight=1.0,
        )
