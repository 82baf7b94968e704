"""``python -m benchmarks restart --path filter``: the filtered live state and the identification without the
core.

What wiring ``service.estimate.state.FilteredState`` into the service would give (``benchmarks.restart``):
samples pushed through the filter from the start index on; the condition's schedule
(``identification.schedule_min`` after the speed change, or after the filter's convergence when that is
later: a (re)start) asks for a window ending then, starting at the latest
filtered snapshot at or before max(condition start, convergence time), at most ``max_window_s`` long and
at least ``min_window_s``; ``model.identify`` fits it from the snapshot's mean with its covariance as
``start_cov`` (and ``start_modes`` fitted directions), warm-started from the condition's previous result.
The filter then uses the new H with its CI's σ(log H) as the considered H error (``set_h(h_rel=...)``).

What the core decides is taken from the core itself, never copied: its configuration
(``service.host.runtime.core_config``: the initial H, the idle speed below which it skips a window, the
schedule, the window lengths, the CI threshold) and the considered H error
(``service.estimate.state.h_rel_from_ci``, ``GUESSED_H_REL`` before the first identification).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from benchmarks.restart_profile import BASELINE_SAMPLES, DT_S, T0, Served
from service.estimate.state import GUESSED_H_REL, h_rel_from_ci
from service.host.runtime import core_config


class FilterRestart:
    """One seed's plant run from one start index: ``run(start)`` -> the served results, oldest first."""

    def __init__(
        self,
        model: Any,
        settings: Any,
        run: Any,
        *,
        seed: int,
        start_modes: int = 0,
        stored_offsets: bool = False,
    ) -> None:
        self.model = model
        self.settings = settings
        self.run_data = run
        self.seed = seed
        self.start_modes = start_modes
        self.stored_offsets = stored_offsets
        self.core = core_config(settings)  # the core's own rules (CoreConfig)
        ok = (np.asarray(run.status) == 0) & np.isfinite(run.temps_c)
        self.usable = ok

    def run(self, start: int) -> list[Served]:
        from service.estimate.state import FilteredState

        run, core = self.run_data, self.core
        offsets, offset_sd = self._offsets(start)
        h0 = np.asarray(core.initial_h, dtype=float)
        state = FilteredState(self.model.rom, self.model.spec, h=h0, dt_s=DT_S, offsets_c=offsets)
        state.set_h(h0, h_rel=GUESSED_H_REL)
        state.initialize(T0 + run.times_s[start], self._inputs(start), run.temps_c[start], self.usable[start])
        schedule = [round(s / DT_S) for s in core.scheduler.schedule_s]
        served: list[Served] = []
        cond_start = start  # after a restart the service's condition starts now (no stored state)
        warm: Any = None
        for k in range(start + 1, run.times_s.size):
            state.push(
                T0 + float(run.times_s[k]),
                ambient_c=float(run.ambient_c[k]),
                speed_rpm=float(run.speed_rpm[k]),
                torque_nm=float(run.torque_nm[k]),
                temps_c=run.temps_c[k],
                usable=self.usable[k],
            )
            speed = float(run.speed_rpm[k - 1])  # the condition of the window ending at sample k
            ready = state.ready_at()
            # the schedule counts from the condition's start, or from the convergence after a (re)start
            origin = None if ready is None else max(cond_start, round((ready - T0) / DT_S))
            if origin is not None and k - origin in schedule and abs(speed) >= core.min_speed_rpm:
                result = self._identify(state, cond_start, k, offsets, offset_sd, warm)
                if result is not None:
                    warm = result
                    lo, hi = result.h_ci95[:, 0], result.h_ci95[:, 1]
                    state.set_h(result.h, h_rel=h_rel_from_ci(result.h, hi))
                    served.append(
                        Served(speed_rpm=speed, h=result.h, lo=lo, hi=hi, end_s=float(run.times_s[k]))
                    )
            if run.speed_rpm[k] != speed:
                cond_start, warm = k, None
                state.mark(T0 + float(run.times_s[k]))
        return served

    def _identify(
        self, state: Any, cond_start: int, end: int, offsets: Any, offset_sd: float, warm: Any
    ) -> Any:
        from model.identify import IdentificationError, IdentifyOptions, Window, identify
        from model.inputs import inputs_from_operation

        run, core = self.run_data, self.core
        ready = state.ready_at()
        if ready is None:
            return None
        t_from = max(
            T0 + float(run.times_s[cond_start]),
            ready,
            T0 + float(run.times_s[end]) - core.scheduler.max_window_s,
        )
        snap = state.field_at(t_from)
        a = round((snap.t - T0) / DT_S)
        if (end - a) * DT_S < core.rules.min_window_s:
            return None
        inputs = inputs_from_operation(
            self.model.spec,
            dt_s=DT_S,
            speed_rpm=run.speed_rpm[a:end],
            torque_nm=run.torque_nm[a:end],
            ambient_c=run.ambient_c[a:end],
        )
        mask = self.usable[a : end + 1].all(axis=0)
        opts = IdentifyOptions(ci_threshold=core.ci_threshold, start_modes=self.start_modes)
        try:
            return identify(
                self.model.rom,
                Window(inputs, run.temps_c[a : end + 1], mask, snap.field_c),
                rng=self.seed,
                spec=self.model.spec,
                warm_start=warm,
                offsets_c=offsets,
                offset_sd_c=offset_sd,
                start_cov=snap.cov,
                options=opts,
            )
        except IdentificationError:
            return None

    def _offsets(self, start: int) -> tuple[np.ndarray | None, float]:
        """A baseline over the idle, cold first 5 min when the start is at minute 0 (or, with
        ``stored_offsets``, at any start: the calibration kept across the restart), else unknown offsets
        (the settings' ``offset_sd_c``)."""
        run = self.run_data
        sd_unknown = float(self.settings.identification.offset_sd_c)
        if (start > 0 and not self.stored_offsets) or run.speed_rpm[:BASELINE_SAMPLES].any():
            return None, sd_unknown
        from model.identify import baseline_offsets

        temps = np.where(self.usable[:BASELINE_SAMPLES], run.temps_c[:BASELINE_SAMPLES], np.nan)
        offsets = np.nan_to_num(baseline_offsets(temps, float(np.mean(run.ambient_c[:BASELINE_SAMPLES]))))
        return offsets, float(
            np.std(run.temps_c[:BASELINE_SAMPLES], axis=0).mean() / np.sqrt(BASELINE_SAMPLES)
        )

    def _inputs(self, k: int) -> tuple[float, float, float]:
        run = self.run_data
        return float(run.ambient_c[k]), float(run.speed_rpm[k]), float(run.torque_nm[k])
