"""The service's identification defaults, in one place: ``service.settings`` (what a user configures),
``service.engine.core.CoreConfig`` and ``service.identify.worker.JobRequest`` all take them from here.

No imports beyond ``model.defaults`` (which has none): settings load fast.
"""

from model.defaults import CI_REL_THRESHOLD

__all__ = ["CARRY_START_ERROR", "CI_REL_THRESHOLD", "ESTIMATE_T0_SHIFT"]

# fit a uniform offset of a window's start field: "initial" only while that field descends from the live
# state's first guess (docs/service.md), "always" or "never"
ESTIMATE_T0_SHIFT = "initial"
# the CIs carry the start field's error (model.carry); false: noise-only CIs, which undercover when chained
CARRY_START_ERROR = True
