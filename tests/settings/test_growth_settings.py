"""``[growth] reference_c``: validated, named in the error, settable from the file and the environment."""

from __future__ import annotations

from pathlib import Path

import pytest

from service.settings import Settings, SettingsError, load_settings


def _write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "chtc.toml"
    path.write_text(text, encoding="utf-8")
    return path


def test_default_is_the_live_states_start() -> None:
    assert Settings().growth.reference_c is None


def test_a_uniform_reference_from_the_file_and_the_environment(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    assert load_settings(_write(tmp_path, "[growth]\nreference_c = 20.5\n")).growth.reference_c == 20.5
    monkeypatch.setenv("CHTC_GROWTH__REFERENCE_C", "19")
    assert load_settings(None).growth.reference_c == 19.0


@pytest.mark.parametrize("value", ["nan", "inf", "500", "-80", '"warm"'])
def test_a_bad_reference_names_the_field(tmp_path: Path, value: str) -> None:
    text = f"[growth]\nreference_c = {value}\n"
    with pytest.raises(SettingsError, match=r"growth\.reference_c: "):
        load_settings(_write(tmp_path, text))


def test_an_unknown_growth_key_is_refused(tmp_path: Path) -> None:
    with pytest.raises(SettingsError, match=r"growth\.reference: unknown key"):
        load_settings(_write(tmp_path, "[growth]\nreference = 20\n"))
