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
    assert s.experimental.rom_rank == 56 and s.model.h_box == (5.0, 200.0)
    assert s.model.rom_cache_dir == tmp_path / "cache"
    assert s.database.url == f"sqlite:///{tmp_path / 'data' / 'chtc.db'}"
    assert s.identification.schedule_min == (7.0, 20.0, 40.0, 60.0)
    assert s.experimental.start_modes == 6 and s.experimental.estimate_loads is False
    assert s.api.token is None


def test_example_file_parses_and_matches_defaults() -> None:
    from_file = load_settings(EXAMPLE)
    defaults = Settings()
    sections = (
        "modbus",
        "can",
        "acquisition",
        "identification",
        "detector",
        "api",
        "database",
        "experimental",
    )
    for section in sections:
        assert getattr(from_file, section) == getattr(defaults, section), section
    assert from_file.model.h_box == defaults.model.h_box


def test_example_file_documents_every_key() -> None:
    text = EXAMPLE.read_text(encoding="utf-8")
    for section, block in Settings().model_dump().items():
        if isinstance(block, list):  # an array of tables: documented with an example entry
            assert f"[[{section}]]" in text, section
            continue
        assert f"[{section}]" in text, section
        for key in block:
            assert f"{key} =" in text, f"{section}.{key}"


def test_configuration_doc_documents_every_key() -> None:
    text = (EXAMPLE.parents[1] / "docs" / "configuration.md").read_text(encoding="utf-8")
    for section, block in Settings().model_dump().items():
        if isinstance(block, list):
            assert f"### `[[{section}]]`" in text, section
            continue
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
        ("[experimental]\ndistance_scales = [1000, 0, 5]\n", "experimental.distance_scales"),
        ('[experimental]\nmode = "speedmap"\n', "experimental.mode"),
        ('[identification]\nmode = "speedmap"\n', "identification.mode"),
        ("[identification]\nmode = 1\n", "identification.mode"),
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
    from service.settings import IDENTIFICATION_METHODS, ExperimentalSettings

    method_type = ExperimentalSettings.model_fields["method"].annotation
    assert set(get_args(method_type)) == set(IDENTIFICATION_METHODS) == set(METHODS)


def test_sections_build_the_pure_cores_configs() -> None:
    from service.core.config import core_config

    cfg = core_config(Settings())
    assert cfg.detector.thresholds == (150.0, 1.0, 1.0)
    assert cfg.scheduler.schedule_s == (420.0, 1200.0, 2400.0, 3600.0)


@pytest.mark.parametrize("path", sorted(EXAMPLE.parent.glob("*.toml")), ids=lambda p: p.name)
def test_every_shipped_config_file_is_valid(path: Path) -> None:
    settings = load_settings(path)
    assert settings.modbus.port > 0


# --- issue 25: an operator's [identification] is short; the research switches are in [experimental] -------
OPERATOR_KEYS = {
    "mode",  # in [experimental] from issue 25 to issue 39: the product's one choice of identification
    "schedule_min",
    "min_window_s",
    "max_window_s",
    "min_good_channels",
    "ci_rel_threshold",
    "timeout_s",
    "offset_calibration",
    "offset_rest_s",
    "offset_sd_c",
    "map_window_min",
    "map_refit_min",
    "map_fresh_min",
}


def test_identification_has_at_most_13_operator_keys() -> None:
    from service.settings import ExperimentalSettings, IdentificationSettings

    keys = set(IdentificationSettings.model_fields)
    assert len(keys) <= 13, sorted(keys)  # 12 and the mode (issue 39)
    assert keys == OPERATOR_KEYS  # a new key is a decision: operator's, or experimental
    assert not keys & set(ExperimentalSettings.model_fields)  # ``--set KEY`` finds one section


def test_an_old_file_setting_a_moved_key_says_where_it_went(tmp_path: Path) -> None:
    """A file written for the 30-key ``[identification]`` (and ``[model] rom_rank``) stops with one line per
    moved key naming its new place, file and environment, not a bare "unknown key"."""
    path = write(
        tmp_path,
        '[identification]\nschedule_min = [7, 20]\nmode = "combined"\nseed = 3\nmap_family = "nodes"\n'
        "[model]\nrom_rank = 56\nh_box = [5.0, 200.0]\n",
    )
    with pytest.raises(SettingsError) as info:
        load_settings(path)
    message = str(info.value)
    for section, key in (("identification", "seed"), ("identification", "map_family"), ("model", "rom_rank")):
        assert f"\n  {section}.{key}: moved to [experimental]" in message, key
        assert f"experimental.{key} (env CHTC_EXPERIMENTAL__{key.upper()})" in message, key
    # the keys that stayed are fine, and the mode is back in [identification] since issue 39
    assert "schedule_min" not in message and "h_box" not in message and ".mode" not in message
    moved = write(
        tmp_path,
        '[identification]\nschedule_min = [7, 20]\nmode = "combined"\n[experimental]\nseed = 3\n'
        'map_family = "nodes"\nrom_rank = 56\n[model]\nh_box = [5.0, 200.0]\n',
    )
    s = load_settings(moved)  # the same values, written where they now live
    assert (s.experimental.seed, s.experimental.rom_rank, s.identification.schedule_min) == (
        3,
        56,
        (7.0, 20.0),
    )


def test_a_moved_key_in_the_environment_says_where_it_went(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("CHTC_EXPERIMENTAL__MODE", "per_condition")  # where the mode was, issues 25 to 39
    with pytest.raises(
        SettingsError,
        match=r"experimental\.mode: moved to \[identification\] in issue 39.*CHTC_IDENTIFICATION__MODE",
    ):
        load_settings(None)
    monkeypatch.delenv("CHTC_EXPERIMENTAL__MODE")
    monkeypatch.setenv("CHTC_IDENTIFICATION__SEED", "3")  # before issue 25
    with pytest.raises(
        SettingsError,
        match=r"identification\.seed: moved to \[experimental\] in issue 25.*CHTC_EXPERIMENTAL__SEED",
    ):
        load_settings(None)
    monkeypatch.delenv("CHTC_IDENTIFICATION__SEED")
    monkeypatch.setenv("CHTC_IDENTIFICATION__MODE", "per_condition")
    monkeypatch.setenv("CHTC_EXPERIMENTAL__ROM_RANK", "46")
    s = load_settings(None)
    assert (s.identification.mode, s.experimental.rom_rank) == ("per_condition", 46)


@pytest.mark.parametrize("key", ["map_start_draws", "map_start_lead_min", "map_live_h_error"])
def test_a_removed_key_says_it_was_removed(tmp_path: Path, key: str) -> None:
    """Measured without effect (docs/design/hmap.md), deleted in issue 25: the error says so, in either
    section."""
    value = '"map"' if key == "map_live_h_error" else "0"
    with pytest.raises(SettingsError, match=rf"identification\.{key}: removed in issue 25: measured without"):
        load_settings(write(tmp_path, f"[identification]\n{key} = {value}\n"))
    with pytest.raises(SettingsError, match=rf"experimental\.{key}: unknown key"):
        load_settings(write(tmp_path, f"[experimental]\n{key} = {value}\n"))


def test_rules_across_sections_name_both_keys(tmp_path: Path) -> None:
    text = "[identification]\nmap_window_min = 5\n[experimental]\nmap_min_window_min = 10\n"
    with pytest.raises(
        SettingsError,
        match=r"\n  experimental\.map_min_window_min \(10\.0\) must be <= "
        r"identification\.map_window_min \(5\.0\)",
    ):
        load_settings(write(tmp_path, text))
    text = "[identification]\nmap_fresh_min = 0.25\n[experimental]\nmap_debounce_s = 30\n"
    with pytest.raises(SettingsError, match=r"identification\.map_fresh_min .* experimental\.map_debounce_s"):
        load_settings(write(tmp_path, text))


def test_the_configuration_docs_minimal_machine_file_is_valid(tmp_path: Path) -> None:
    """docs/configuration.md "What to set for a real machine" shows a minimal file: it must load."""
    text = (EXAMPLE.parents[1] / "docs" / "configuration.md").read_text(encoding="utf-8")
    block = text.split("A minimal file for one spindle:", 1)[1].split("```toml\n", 1)[1].split("```", 1)[0]
    s = load_settings(write(tmp_path, block))
    assert (s.modbus.port, s.can.interface, s.compensation.reference_c) == (502, "socketcan", 20.0)
    assert s.experimental == Settings().experimental
