"""Settings: defaults, TOML file, environment overrides and their precedence, errors naming the key."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from service.settings import Settings, SettingsError, load_settings

EXAMPLE = Path(__file__).resolve().parents[2] / "deploy" / "chtc.example.toml"


@pytest.fixture(autouse=True)
def clean_env(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> Path:
    for name in list(os.environ):
        if name.upper().startswith("CHTC_"):
            monkeypatch.delenv(name)
    monkeypatch.setenv("CHTC_DATA_DIR", str(tmp_path / "data"))
    monkeypatch.setenv("CHTC_CACHE_DIR", str(tmp_path / "cache"))
    return tmp_path


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "chtc.toml"
    path.write_text(text, encoding="utf-8")
    return path


def test_defaults_work_without_a_file(tmp_path: Path) -> None:
    s = Settings()
    assert (s.modbus.host, s.modbus.port, s.modbus.unit) == ("127.0.0.1", 5020, None)
    assert s.can.interface == "virtual"
    assert s.model.rom_rank == 56 and s.model.h_box == (5.0, 200.0)
    assert s.model.rom_cache_dir == tmp_path / "cache"
    assert s.database.url == f"sqlite:///{tmp_path / 'data' / 'chtc.db'}"
    assert s.identification.schedule_min == (7.0, 20.0, 40.0, 60.0)
    assert s.identification.start_modes == 6 and s.identification.estimate_loads is False
    assert s.api.token is None


def test_example_file_parses_and_matches_defaults() -> None:
    from_file = load_settings(EXAMPLE)
    defaults = Settings()
    for section in ("modbus", "can", "acquisition", "identification", "detector", "api", "database"):
        assert getattr(from_file, section) == getattr(defaults, section), section
    assert from_file.model.h_box == defaults.model.h_box


def test_example_file_documents_every_key() -> None:
    text = EXAMPLE.read_text(encoding="utf-8")
    for section, block in Settings().model_dump().items():
        assert f"[{section}]" in text, section
        for key in block:
            assert f"{key} =" in text, f"{section}.{key}"


def test_configuration_doc_documents_every_key() -> None:
    text = (EXAMPLE.parents[1] / "docs" / "configuration.md").read_text(encoding="utf-8")
    for section, block in Settings().model_dump().items():
        assert f"### `[{section}]`" in text, section
        for key in block:
            assert f"| `{key}` |" in text, f"{section}.{key}"


def test_keyword_dict_overrides_merge_with_env(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("CHTC_API__HOST", "10.0.0.9")
    s = load_settings(None, api={"port": 9100})
    assert (s.api.host, s.api.port) == ("10.0.0.9", 9100)


def test_toml_values_are_used(tmp_path: Path) -> None:
    path = write(tmp_path, '[modbus]\nhost = "10.1.2.3"\nport = 502\n[api]\ntoken = "s3cret-s3cret-s3cret"\n')
    s = load_settings(path)
    assert (s.modbus.host, s.modbus.port) == ("10.1.2.3", 502)
    assert s.modbus.timeout_s == Settings().modbus.timeout_s
    assert s.api.token is not None and s.api.token.get_secret_value() == "s3cret-s3cret-s3cret"
    assert "s3cret" not in repr(s) and "s3cret" not in str(s.redacted())


def test_env_overrides_file_key_by_key(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = write(tmp_path, '[modbus]\nhost = "10.1.2.3"\nport = 502\n')
    monkeypatch.setenv("CHTC_MODBUS__PORT", "1502")
    monkeypatch.setenv("CHTC_DATABASE__URL", "postgresql+psycopg://u:pw@db:5432/chtc")
    monkeypatch.setenv("CHTC_IDENTIFICATION__SCHEDULE_MIN", "[10, 15]")
    s = load_settings(path)
    assert s.modbus.port == 1502  # env wins
    assert s.modbus.host == "10.1.2.3"  # the file's other key in the same section survives
    assert s.database.url.startswith("postgresql+psycopg://")
    assert "pw" not in s.redacted()["database"]["url"]
    assert s.identification.schedule_min == (10.0, 15.0)
    assert s.identification.schedule_s == (600.0, 900.0)


def test_keyword_overrides_beat_env(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("CHTC_API__PORT", "9000")
    assert Settings().api.port == 9000
    assert load_settings(None, api={"port": 9100}).api.port == 9100


def test_unrelated_chtc_env_vars_are_ignored(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("CHTC_TEST_PG_URL", "postgresql+psycopg://x@y/z")
    assert Settings().modbus.port == 5020


def test_relative_paths_resolve_against_the_file(tmp_path: Path) -> None:
    path = write(tmp_path, '[can]\ndbc = "dev/spindle.dbc"\n[model]\nrom_cache_dir = "cache"\n')
    s = load_settings(path)
    assert s.can.dbc == tmp_path / "dev" / "spindle.dbc"
    assert s.model.rom_cache_dir == tmp_path / "cache"


@pytest.mark.parametrize(
    ("text", "key"),
    [
        ("[modbus]\nport = 70000\n", "modbus.port"),
        ('[can]\ninterface = "peak"\n', "can.interface"),
        ("[modbus]\nunit = 248\n", "modbus.unit"),
        ("[can]\noptions = { bitrate = 250000 }\n", "can.options"),
        ("[model]\nh_box = [200.0, 5.0]\n", "model.h_box"),
        ("[identification]\nschedule_min = [20, 10]\n", "identification.schedule_min"),
        ("[modbus]\nprot = 502\n", "modbus.prot"),
        ("[modbuss]\nport = 502\n", "modbuss"),
        ('[database]\nurl = "not a url"\n', "database.url"),
        ("[database]\nretry_initial_s = 10\nretry_max_s = 1\n", "database"),
        ("[identification]\nschedule_min = [5, 60]\n", "identification"),
        ("[identification]\nmax_window_s = 300\n", "identification"),
        ("[identification]\ndistance_scales = [1000, 0, 5]\n", "identification.distance_scales"),
    ],
)
def test_errors_name_the_key(tmp_path: Path, text: str, key: str) -> None:
    with pytest.raises(SettingsError) as info:
        load_settings(write(tmp_path, text))
    message = str(info.value)
    assert f"\n  {key}: " in message
    assert str(tmp_path / "chtc.toml") in message


def test_env_errors_name_the_key(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("CHTC_DETECTOR__HOLD_S", "-1")
    with pytest.raises(SettingsError, match=r"detector\.hold_s: "):
        load_settings(None)


def test_secret_values_never_appear_in_errors(tmp_path: Path) -> None:
    with pytest.raises(SettingsError) as info:
        load_settings(write(tmp_path, "[api]\ntoken = 12345\n"))
    assert "api.token" in str(info.value) and "12345" not in str(info.value)


def test_toml_syntax_error_names_file_and_line(tmp_path: Path) -> None:
    path = write(tmp_path, "[modbus]\nport = 502\nhost = \n")
    with pytest.raises(SettingsError, match=r"chtc\.toml: invalid TOML: .*line 3"):
        load_settings(path)


def test_missing_file_is_a_settings_error(tmp_path: Path) -> None:
    with pytest.raises(SettingsError, match="cannot read config file"):
        load_settings(tmp_path / "absent.toml")


def test_empty_token_means_unset(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("CHTC_API__TOKEN", "  ")
    assert Settings().api.token is None


def test_methods_match_the_model() -> None:
    from typing import get_args

    from model.identify import METHODS
    from service.settings import IDENTIFICATION_METHODS, IdentificationSettings

    method_type = IdentificationSettings.model_fields["method"].annotation
    assert set(get_args(method_type)) == set(IDENTIFICATION_METHODS) == set(METHODS)


def test_sections_build_the_pure_cores_configs() -> None:
    from service.identify.detector import DetectorConfig
    from service.identify.scheduler import SchedulerConfig

    s = Settings()
    detector = DetectorConfig(**s.detector.model_dump())
    assert detector.thresholds == (150.0, 1.0, 1.0)
    ident = s.identification
    sched = SchedulerConfig(
        min_data_s=ident.min_window_s,
        schedule_s=ident.schedule_s,
        max_window_s=ident.max_window_s,
        distance_scales=ident.distance_scales,
    )
    assert sched.schedule_s == (420.0, 1200.0, 2400.0, 3600.0)


@pytest.mark.parametrize("path", sorted(EXAMPLE.parent.glob("*.toml")), ids=lambda p: p.name)
def test_every_shipped_config_file_is_valid(path: Path) -> None:
    settings = load_settings(path)
    assert settings.modbus.port > 0
