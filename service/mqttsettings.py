"""The ``[mqtt]`` settings section (docs/configuration.md, docs/integration.md "MQTT"): off by default.

A leaf below both ``service.settings`` (which names the section) and the outlet (``service.serve.mqtt``), so
neither imports the other's package; nothing here opens a socket.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, SecretStr, field_validator, model_validator

__all__ = ["MqttDeadbands", "MqttSettings", "MqttTls"]

# Sparkplug B ids and a topic level: no MQTT wildcards, no level separator (Sparkplug 3.0, "Topic Namespace")
_ID = re.compile(r"^[^/+#\s]+$")


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class MqttTls(_Section):
    """TLS to the broker: on when ``enabled`` (or any file is given); the system's CAs unless ``ca``."""

    enabled: bool = False
    ca: Path | None = None  # PEM CA bundle that signed the broker's certificate
    cert: Path | None = None  # client certificate (PEM) for brokers that require one ...
    key: Path | None = None  # ... and its private key
    insecure: bool = False  # skip the broker's hostname check (a test broker's self-signed certificate)

    @model_validator(mode="after")
    def _cert_with_key(self) -> MqttTls:
        if (self.cert is None) != (self.key is None):
            raise ValueError("cert and key go together")
        return self

    @property
    def active(self) -> bool:
        return self.enabled or self.ca is not None or self.cert is not None


class MqttDeadbands(_Section):
    """A number is published again when it moved by more than its deadband (absolute, in its unit) since
    the last value sent; a status, a flag or a reason is sent on every change."""

    h_w_m2k: float = Field(default=0.5, ge=0)  # H1-H7 and their CI bounds, W/(m²·K)
    growth_um: float = Field(default=0.1, ge=0)  # growth, CI, correction, µm (the PLC's 0.1 µm step)
    mm: float = Field(default=0.0001, ge=0)  # SD43900 / SD42960, mm (0.1 µm)
    speed_rpm: float = Field(default=10.0, ge=0)  # the condition's speed, min⁻¹
    torque_nm: float = Field(default=0.1, ge=0)  # the condition's torque, N·m
    temperature_c: float = Field(default=0.05, ge=0)  # the condition's ambient, °C
    age_s: float = Field(default=5.0, ge=0)  # the newest sample's age, s
    other: float = Field(default=0.0, ge=0)  # every other number (counters, fit)


class MqttSettings(_Section):
    """The MQTT outlet: Sparkplug B (edge node = this instance, device = the spindle) or plain JSON
    (retained topics ``{topic_prefix}/{device_id}/...``). ``device_id`` defaults to the spindle's id
    (``for_spindle``)."""

    enabled: bool = False
    mode: Literal["sparkplug", "json"] = "sparkplug"
    host: str = "127.0.0.1"
    port: int = Field(default=1883, ge=1, le=65535)  # 8883 for TLS, usually
    client_id: str | None = None  # None: "chtc-{edge_node_id}" (Sparkplug) / "chtc-{device}" (JSON)
    username: str | None = None
    password: SecretStr | None = None
    tls: MqttTls = Field(default_factory=MqttTls)
    keepalive_s: int = Field(default=30, ge=5, le=65535)  # the broker sends the Will after 1.5 × this silent
    group_id: str = "chtc"  # Sparkplug group
    edge_node_id: str = "chtc-1"  # Sparkplug edge node: this instance
    device_id: str | None = None  # Sparkplug device (and the JSON topics' level); None: spindle.id
    topic_prefix: str = "chtc"  # JSON mode: {topic_prefix}/{device_id}/...
    buffer_messages: int = Field(default=1000, ge=1)  # kept while the broker is away (oldest dropped)
    deadbands: MqttDeadbands = Field(default_factory=MqttDeadbands)
    tick_s: float = Field(default=5.0, gt=0, le=3600)  # re-judged this often without a new view (ages)
    backoff_initial_s: float = Field(default=1.0, gt=0)  # reconnect: first wait, doubled per failure ...
    backoff_max_s: float = Field(default=30.0, gt=0)  # ... up to this
    rebirth_min_interval_s: float = Field(default=10.0, ge=0)  # NCMD rebirths closer than this: ignored
    state_dir: Path | None = None  # where bdSeq is kept across restarts (None: the data directory)

    @field_validator("group_id", "edge_node_id", "device_id")
    @classmethod
    def _plain_id(cls, value: str | None) -> str | None:
        if value is not None and not _ID.match(value):
            raise ValueError(f"{value!r}: no '/', '+', '#' or spaces (one MQTT topic level)")
        return value

    @field_validator("topic_prefix")
    @classmethod
    def _plain_prefix(cls, value: str) -> str:
        levels = value.split("/")
        if not all(_ID.match(level) for level in levels):
            raise ValueError(f"{value!r}: topic levels without '+', '#', spaces or empty levels")
        return value

    @field_validator("password", mode="before")
    @classmethod
    def _empty_is_unset(cls, value: object) -> object:
        return None if isinstance(value, str) and not value else value

    @model_validator(mode="after")
    def _backoff_order(self) -> MqttSettings:
        if self.backoff_max_s < self.backoff_initial_s:
            raise ValueError("backoff_max_s must be >= backoff_initial_s")
        return self

    def for_spindle(self, spindle_id: str) -> MqttSettings:
        """This section with ``device_id`` set: as given, else ``spindle_id`` (the instance's ``spindle.id``,
        whose pattern is a valid Sparkplug id and topic level)."""
        return self if self.device_id is not None else self.model_copy(update={"device_id": spindle_id})

    @property
    def device(self) -> str:
        """The Sparkplug device id (the JSON topics' level); ``ValueError`` until :meth:`for_spindle`."""
        if self.device_id is None:
            raise ValueError("mqtt.device_id: unset; resolve it with for_spindle(spindle.id)")
        return self.device_id

    @property
    def effective_client_id(self) -> str:
        if self.client_id:
            return self.client_id
        return f"chtc-{self.edge_node_id if self.mode == 'sparkplug' else self.device}"
