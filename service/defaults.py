"""The service's identification defaults, in one place: ``service.settings`` (what a user configures),
``service.engine.core.CoreConfig`` and ``service.identify.worker.JobRequest`` all take them from here.

No imports beyond ``model.defaults`` (which has none): settings load fast.
"""

from model.defaults import CI_REL_THRESHOLD

__all__ = ["CARRY_START_ERROR", "CI_REL_THRESHOLD", "START_MODES"]

# windows start from the filtered live state: fit its leading uncertain directions too
# (docs/design/estimator.md, "Identification after a restart": without them the restarted H6/H7 are 1.5-4x
# worse)
START_MODES = 6
# the CIs carry the start field's error (model.carry); false: noise-only CIs, which undercover when chained
CARRY_START_ERROR = True
