"""Weak API tokens are refused at start-up (settings load) with a message that names the key, never the
token; surrounding whitespace (a secret file's newline) is stripped so the token can match."""

from __future__ import annotations

from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from service.settings import Settings, SettingsError, load_settings
from service.shell.service import SoftSensorService
from tests.api.conftest import ManualClock

REPO = Path(__file__).resolve().parents[2]


def _env_example_token() -> str:
    for line in (REPO / "deploy" / "env.example").read_text().splitlines():
        if line.startswith("CHTC_API_TOKEN="):
            return line.partition("=")[2]
    raise AssertionError("deploy/env.example has no CHTC_API_TOKEN")


@pytest.mark.parametrize("key", ["token", "read_token"])
@pytest.mark.parametrize("weak", ["q", "fifteen-chars-q", "change-me", "change-me-change-me-change-me"])
def test_weak_token_is_refused_naming_the_key(tmp_path: Path, key: str, weak: str) -> None:
    path = tmp_path / "chtc.toml"
    path.write_text(f'[api]\n{key} = "{weak}"\n')
    with pytest.raises(SettingsError) as info:
        load_settings(path)
    text = str(info.value)
    assert f"api.{key}" in text and weak not in text
    assert "too short" in text or "placeholder" in text


def test_the_env_example_placeholder_is_refused(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("CHTC_API__TOKEN", _env_example_token())
    with pytest.raises(ValueError, match=r"api\.token") as info:
        Settings()
    assert _env_example_token() not in str(info.value)  # not even in pydantic's own message


def test_surrounding_whitespace_is_stripped_and_the_token_matches(
    monkeypatch: pytest.MonkeyPatch, service: SoftSensorService, clock: ManualClock
) -> None:
    token = "0123456789abcdef0123"
    monkeypatch.setenv("CHTC_API__TOKEN", f"  {token}\n")
    settings = Settings()
    assert settings.api.token is not None and settings.api.token.get_secret_value() == token
    with TestClient(create_app(settings, service, clock=clock)) as c:
        r = c.post("/api/v1/identifications", headers={"Authorization": f"Bearer {token}"})
    assert r.status_code == 202, r.text
