"""``compensation.reference_c`` (``[growth] reference_c`` until issue 39): validated, named in the error,
settable from the file and the environment; the old place gets the "moved to" error."""

from __future__ import annotations

from pathlib import Path

import pytest

from service.settings import Settings, SettingsError, load_settings


def _write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "chtc.toml"
    path.write_text(text, encoding="utf-8")
    return path


def test_default_is_the_live_states_start() -> None:
    assert Settings().compensation.reference_c is None


def test_a_uniform_reference_from_the_file_and_the_environment(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    text = "[compensation]\nreference_c = 20.5\n"
    assert load_settings(_write(tmp_path, text)).compensation.reference_c == 20.5
    monkeypatch.setenv("CHTC_COMPENSATION__REFERENCE_C", "19")
    assert load_settings(None).compensation.reference_c == 19.0


@pytest.mark.parametrize("value", ["nan", "inf", "500", "-80", '"warm"'])
def test_a_bad_reference_names_the_field(tmp_path: Path, value: str) -> None:
    text = f"[compensation]\nreference_c = {value}\n"
    with pytest.raises(SettingsError, match=r"compensation\.reference_c: "):
        load_settings(_write(tmp_path, text))


def test_the_old_growth_section_says_where_its_key_went(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """An old file's ``[growth]`` and an old ``CHTC_GROWTH__REFERENCE_C`` fail naming the new key (pydantic
    alone would ignore the variable of a section that no longer exists)."""
    moved = r"growth\.reference_c moved to \[compensation\] in issue 39.*compensation\.reference_c"
    with pytest.raises(SettingsError, match=rf"\n  growth: the section \[growth\] is gone .*{moved}"):
        load_settings(_write(tmp_path, "[growth]\nreference_c = 20.5\n"))
    monkeypatch.setenv("CHTC_GROWTH__REFERENCE_C", "19")
    with pytest.raises(SettingsError, match=rf"{moved}.*CHTC_COMPENSATION__REFERENCE_C"):
        load_settings(None)
    with pytest.raises(ValueError, match=r"growth\n  Extra inputs are not permitted"):  # not ignored
        Settings()


def test_an_unknown_growth_key_is_refused(tmp_path: Path) -> None:
    with pytest.raises(SettingsError, match=r"growth\.reference: unknown key"):
        load_settings(_write(tmp_path, "[growth]\nreference = 20\n"))
