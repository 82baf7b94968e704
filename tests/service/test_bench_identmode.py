"""``benchmarks.identmode``: the identification mode and settings a bench runs with (--mode, --set)."""

from __future__ import annotations

import argparse

import pytest

from benchmarks import identmode
from service.settings import Settings


def test_the_mode_defaults_to_the_settings_and_can_be_chosen(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("CHTC_IDENTIFICATION__MODE", raising=False)
    assert identmode.bench_settings(None).identification.mode == Settings().identification.mode
    for mode in identmode.MODES:
        s = identmode.bench_settings(mode, {"map_min_window_min": 7, "schedule_min": [7, 20, 40]})
        assert s.identification.mode == mode
        assert s.experimental.map_min_window_min == 7.0 and s.identification.schedule_min == (
            7.0,
            20.0,
            40.0,
        )
    s = identmode.bench_settings(None, {"rom_rank": 46, "experimental.seed": 3, "map_fresh_min": 20})
    assert (s.experimental.rom_rank, s.experimental.seed, s.identification.map_fresh_min) == (46, 3, 20.0)
    monkeypatch.setenv("CHTC_IDENTIFICATION__MODE", "speed_map")  # the environment is the settings' own
    assert identmode.bench_settings(None).identification.mode == "speed_map"
    assert identmode.bench_settings("per_condition").identification.mode == "per_condition"


def test_bad_settings_are_named() -> None:
    with pytest.raises(ValueError, match=r"unknown setting nope"):
        identmode.bench_settings(None, {"nope": 1})
    with pytest.raises(ValueError, match=r"unknown setting map_start_draws: removed"):
        identmode.bench_settings(None, {"map_start_draws": 16})
    with pytest.raises(ValueError, match=r"unknown setting identification\.rom_rank"):
        identmode.bench_settings(None, {"identification.rom_rank": 46})  # it is experimental's
    with pytest.raises(ValueError, match="map_min_window_min"):
        identmode.bench_settings("speed_map", {"map_min_window_min": 90})  # > map_window_min
    with pytest.raises(ValueError, match="expected KEY=VALUE"):
        identmode.parse_sets(["map_min_window_min"])
    assert identmode.parse_sets(["a=7", "b=[1, 2]", "c=nodes"]) == {"a": 7, "b": [1, 2], "c": "nodes"}


def test_arguments() -> None:
    parser = argparse.ArgumentParser()
    identmode.add_arguments(parser)
    args = parser.parse_args(["--mode", "per_condition", "--set", "a=1", "--set", "b=2"])
    assert args.ident_mode == "per_condition" and args.set == ["a=1", "b=2"]
    assert parser.parse_args([]).ident_mode is None
    with pytest.raises(SystemExit):
        parser.parse_args(["--mode", "speedmap"])
