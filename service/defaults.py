"""The service's identification defaults, in one place: ``service.settings`` (what a user configures),
``service.core.machine.CoreConfig`` and ``service.identify.worker.JobRequest`` all take them from here.

No imports beyond ``model.defaults`` (which has none): settings load fast.
"""

from model.defaults import CI_REL_THRESHOLD

__all__ = ["CARRY_START_ERROR", "CI_REL_THRESHOLD", "H_FORM_SD_LN", "H_NO_BASELINE_SD_LN", "START_MODES"]

# 1σ in ln H of what no statistical band of a served H sees: the service's coarser mesh, its lumped bearings
# and the speed map's shape against the machine's (docs/design/policy.md, "The served H band"). Measured on
# the compensation bench's tuning seeds 0-3: flagged H missed their random truth by up to 1.2σ of their
# own band (z table there); checked on held-out seeds. Added in quadrature to every band /chtc serves.
H_FORM_SD_LN = 0.15

# 1σ in ln H added (in quadrature, on top of H_FORM_SD_LN) to every served H band and to the live state's
# considered H error while offset calibration is on but no baseline exists (a start on a warm spindle with an
# empty database): the fits then marginalise 32 unknown channel offsets, read H from the transients alone
# and start from a filtered field that has not seen the shaft; their bands missed the random truth by up to
# 2.6σ (docs/design/estimator.md, "Warm restart with no stored state", z table). Measured on the bench's
# restart_no_state at seeds 300-305 and 110 (RMS z 1.05-1.3 → ~1 needs 0.09-0.27); checked on held-out seeds.
H_NO_BASELINE_SD_LN = 0.25

# windows start from the filtered live state: fit its leading uncertain directions too
# (docs/design/estimator.md, "Identification after a restart": without them the restarted H6/H7 are 1.5-4x
# worse)
START_MODES = 6
# the CIs carry the start field's error (model.carry); false: noise-only CIs, which undercover when chained
CARRY_START_ERROR = True
