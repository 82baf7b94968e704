"""One declaration per setting (issue 39): the engine's configuration objects have no defaults of their own
(``CoreConfig()`` used to disagree with ``core_config(Settings())`` in 8 places), and the configuration built
from ``Settings()`` equals the one built from the documented defaults, ``deploy/chtc.example.toml``, loaded
through the same settings loader."""

from __future__ import annotations

import dataclasses
import tomllib
import typing
from pathlib import Path

import pytest

from service.acquire.calibration import CalibrationConfig
from service.core.config import CoreConfig, compensation_limits, control_limits, core_config
from service.estimate.state import FilterSettings
from service.identify.detector import DetectorConfig
from service.identify.scheduler import SchedulerConfig
from service.identify.speedmap import MapConfig
from service.identify.window import WindowRules
from service.modelload import ModelRef
from service.serve.cigate import CiGateLimits
from service.serve.controlled import ControlLimits
from service.serve.policy import CompensationLimits
from service.settings import Settings, load_settings

EXAMPLE = Path(__file__).resolve().parents[2] / "deploy" / "chtc.example.toml"

# the sections the engine's configuration is built from (and the keys of [database] it reads)
ENGINE_SECTIONS = ("identification", "detector", "acquisition", "experimental", "compensation", "controller")
ENGINE_DATABASE_KEYS = ("sample_store_period_s", "live_checkpoint_s")

# dataclasses reachable from the engine's configuration that keep defaults, and why: each has no settings
# key, so its defaults are its one declaration (``core_config`` passes ``FilterSettings()``)
EXEMPT: dict[type, str] = {
    FilterSettings: "the live state's filter tuning (docs/design/estimator.md): no key"
}


@pytest.fixture
def no_env(monkeypatch: pytest.MonkeyPatch) -> None:
    """Defaults only: no ``CHTC_*`` variable of the machine running the tests."""
    import os

    for name in list(os.environ):
        if name.upper().startswith("CHTC_"):
            monkeypatch.delenv(name)


def test_the_engine_configuration_from_settings_is_the_documented_one(no_env: None) -> None:
    documented = load_settings(EXAMPLE)
    defaults = Settings()
    assert core_config(documented) == core_config(defaults)
    assert compensation_limits(documented.compensation) == compensation_limits(defaults.compensation)
    assert control_limits(documented) == control_limits(defaults)
    assert ModelRef.from_settings(documented) == ModelRef.from_settings(defaults)
    assert documented.compensation.reference_c == defaults.compensation.reference_c is None


def test_the_documented_file_writes_out_every_key_the_engine_reads() -> None:
    """The comparison above is not vacuous: every key of the engine's sections with a value as its default
    is written out in the example (a commented-out key would be compared with itself)."""
    data = tomllib.loads(EXAMPLE.read_text(encoding="utf-8"))
    missing = []
    for section in ENGINE_SECTIONS:
        for key, field in Settings.model_fields[section].annotation.model_fields.items():  # type: ignore[union-attr]
            default = field.get_default(call_default_factory=True)
            if default is not None and key not in data.get(section, {}):
                missing.append(f"{section}.{key}")
    missing += [f"database.{k}" for k in ENGINE_DATABASE_KEYS if k not in data["database"]]
    assert not missing, missing


def _engine_config_classes() -> set[type]:
    """The dataclasses the engine's configuration is made of: ``CoreConfig``, the dataclasses its fields hold
    (recursively), the policy's limits and the model's reference."""
    found: set[type] = set()
    todo: list[type] = [CoreConfig, CompensationLimits, ControlLimits, ModelRef]
    while todo:
        cls = todo.pop()
        if cls in found or cls in EXEMPT:
            continue
        found.add(cls)
        for hint in typing.get_type_hints(cls).values():
            for arg in (hint, *typing.get_args(hint)):
                if isinstance(arg, type) and dataclasses.is_dataclass(arg):
                    todo.append(arg)
    return found


def test_no_engine_configuration_class_has_defaults_of_its_own() -> None:
    classes = _engine_config_classes()
    assert {
        CoreConfig,
        DetectorConfig,
        SchedulerConfig,
        WindowRules,
        CalibrationConfig,
        MapConfig,
        CompensationLimits,
        ControlLimits,
        CiGateLimits,
        ModelRef,
    } <= classes
    with_defaults = [
        f"{cls.__name__}.{f.name}"
        for cls in classes
        for f in dataclasses.fields(cls)  # type: ignore[arg-type]
        if f.default is not dataclasses.MISSING or f.default_factory is not dataclasses.MISSING
    ]
    assert not with_defaults, with_defaults
    with pytest.raises(TypeError, match="missing"):
        CoreConfig()  # type: ignore[call-arg]
