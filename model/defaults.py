"""Defaults shared by the identification (``model.identify``) and the service's settings, kept in one place.

No imports: ``service.settings`` reads these without loading numpy or scipy.
"""

CI_REL_THRESHOLD = 0.5  # 1.96·σ(log H) (≈ relative 95 % half-width) above which H is "not identified"
BOUND_REL_TOL = 1e-3  # an H within this fraction of the box width of a bound is "at the bound"
