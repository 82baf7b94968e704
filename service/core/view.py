"""Moved to :mod:`service.serve.view` (issue 28: the outlets read views; ``serve`` may not import ``engine``).
Re-exported here for the engine's modules and existing imports."""

from service.serve.view import CoreView, NewestSample

__all__ = ["CoreView", "NewestSample"]
