"""Fixtures of the service tests: the service's model (FE + cached reduced model) and virtual-plant runs.

The reduced model is read from the same cache directory the service uses (``Settings().model.rom_cache_dir``,
overridable with ``CHTC_CACHE_DIR``); the first run on a fresh machine builds it (about a minute).
"""

from __future__ import annotations

from datetime import UTC, datetime

import pytest

from drivers.ringbuffer import RingBuffer, Sample
from model.geometry import load_spindle
from model.plant import PlantRun, Segment, VirtualPlant
from service.modelload import LoadedModel, ModelRef, load_model
from service.settings import Settings
from simulator.plantsamples import samples_from_plant

T0 = datetime(2026, 1, 5, 8, 0, 0, tzinfo=UTC).timestamp()


@pytest.fixture(scope="session")
def model_ref() -> ModelRef:
    return ModelRef.from_settings(Settings())


@pytest.fixture(scope="session")
def loaded_model(model_ref: ModelRef) -> LoadedModel:
    return load_model(model_ref)


def plant_run(profile: list[Segment], *, seed: int = 1, mesh_size_m: float = 0.004, **kw: object) -> PlantRun:
    """A virtual-plant run (coarser plant mesh than the service's default plant, for speed)."""
    return VirtualPlant(load_spindle(), mesh_size_m=mesh_size_m, seed=seed, **kw).run(profile)  # type: ignore[arg-type]


def samples_of(run: PlantRun, *, t0: float = T0) -> list[Sample]:
    """The run as acquisition samples (quality from the DAQ status: 0 ok, 1 open circuit, 2 out of range)."""
    return samples_from_plant(run, t0_s=t0)


def ring_of(capacity: int = 4000) -> RingBuffer:
    return RingBuffer(capacity, 32)


def inline_service(
    model: LoadedModel, settings: Settings, samples: list[Sample], *, writer=None, restored=None
):
    """The real shell and core with ``settings``, the identification run inline (``run_job``, no worker
    process) and a manual clock at the first sample: ``(service, clock)``."""
    from service.core.machine import ServiceCore
    from service.host.runtime import core_config
    from service.identify.worker import run_job
    from service.shell.service import SoftSensorService
    from simulator.served import ManualClock

    core = ServiceCore(core_config(settings), model=model, history_capacity=10_000, restored=restored)
    clock = ManualClock(samples[0].t)
    svc = SoftSensorService(
        core,
        worker=None,
        writer=writer,
        clock=clock,
        on_event=lambda _m: None,
        run_job=lambda req: run_job(model, req),
    )
    return svc, clock
