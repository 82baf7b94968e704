"""``chtc prebuild``: builds the cache the service then finds, reports it, and fails clearly.

A coarse mesh and a low rank keep the build to seconds; the contract under test (same cache key as the
service's ``load_model``) does not depend on the size.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from service.cli import main as chtc
from service.modelload import ModelRef, load_model
from service.settings import load_settings

SMALL = '[model]\nrom_cache_dir = "cache"\n[experimental]\nmesh_size_m = 0.015\nrom_rank = 4\n'


@pytest.fixture
def small_config(tmp_path: Path) -> Path:
    path = tmp_path / "chtc.toml"
    path.write_text(SMALL)
    return path


@pytest.mark.slow
def test_prebuild_fills_the_cache_the_service_loads(
    small_config: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert chtc(["prebuild", "--config", str(small_config), "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    cache = small_config.parent / "cache"
    assert report["from_cache"] is False and report["rom_rank"] == 4
    assert Path(report["cache_file"]).parent == cache.resolve()
    assert [p.name for p in cache.iterdir()] == [Path(report["cache_file"]).name]

    settings = load_settings(small_config)
    loaded = load_model(ModelRef.from_settings(settings))
    assert loaded.rom.from_cache and loaded.rom.key == report["cache_key"]

    assert chtc(["prebuild", "--config", str(small_config), "--json"]) == 0
    again = json.loads(capsys.readouterr().out)
    assert again["from_cache"] is True and again["cache_key"] == report["cache_key"]


@pytest.mark.slow
def test_cache_dir_option_overrides_the_settings(
    small_config: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    other = tmp_path / "elsewhere"
    assert chtc(["prebuild", "--config", str(small_config), "--cache-dir", str(other), "--quiet"]) == 0
    out = capsys.readouterr().out
    assert str(other.resolve()) in out and "rank 4" in out
    assert not (tmp_path / "cache").exists()


def test_bad_settings_exit_1_naming_the_key(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "bad.toml"
    path.write_text("[experimental]\nrom_rank = 0\n")
    assert chtc(["prebuild", "--config", str(path)]) == 1
    assert "experimental.rom_rank: Input should be greater than or equal to 1" in capsys.readouterr().err


def test_cache_dir_that_is_a_file_exits_2(
    small_config: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("")
    assert chtc(["prebuild", "--config", str(small_config), "--cache-dir", str(blocker / "sub")]) == 2
    assert str(blocker / "sub") in capsys.readouterr().err
