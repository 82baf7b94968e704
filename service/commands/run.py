"""``chtc run --config FILE``: the soft sensor against real devices, with the API and the dashboard.

Settings come from the TOML file and ``CHTC_<SECTION>__<KEY>`` environment variables (``service.settings``).
The Modbus DAQ is ``modbus.host:port`` (register map ``modbus.register_map`` or the default of
docs/drivers.md, "Device contract"), the speed/torque sensor any python-can interface
(``can.interface``/``can.channel``); the API listens on ``api.host:api.port`` (``--host``/``--port``
override them; a busy port is reported before the model loads). A SQLite database (a file of this one
service) is created and upgraded at start; ``--migrate`` does the same for PostgreSQL, whose schema is
shared and upgraded only when the operator says so (docs/design/persistence.md, "Migrations"). Migrations are
retried in the background while the database is unreachable; records are buffered meanwhile. Stops cleanly
on SIGINT/SIGTERM.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import signal
import sys
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from drivers.can_sensor import CanSpindleSensor
    from drivers.modbus_daq import ModbusDaq
    from service.host.runtime import ScaledClock
    from service.settings import Settings

from service.commands._common import (
    CommandError,
    check_database_url,
    check_listens,
    override,
    port_number,
)
from service.shell.heap import freeze_startup_heap

log = logging.getLogger("chtc")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--config",
        type=Path,
        default=None,
        help="settings TOML; env CHTC_<SECTION>__<KEY> overrides it (default: built-in defaults)",
    )
    parser.add_argument(
        "--host", default=None, help="API/dashboard host (default: api.host of the settings, 127.0.0.1)"
    )
    parser.add_argument(
        "--port", type=port_number, default=None, help="API/dashboard port (default: api.port, 8000)"
    )
    parser.add_argument(
        "--migrate",
        action="store_true",
        help="create or upgrade a PostgreSQL schema before starting (SQLite: always done)",
    )
    parser.add_argument("--print-config", action="store_true", help="print the effective settings and exit")


def make_device_drivers(settings: Settings, *, clock: ScaledClock) -> tuple[ModbusDaq, CanSpindleSensor]:
    """The production drivers from ``settings.modbus`` / ``settings.can``."""
    from drivers.can_sensor import CanSpindleSensor
    from drivers.modbus_daq import ModbusDaq
    from drivers.registers import load_register_map

    m, c = settings.modbus, settings.can
    daq = ModbusDaq(
        m.host,
        m.port,
        register_map=load_register_map(m.register_map) if m.register_map is not None else None,
        timeout_s=m.timeout_s,
        stale_after_s=max(30.0, 3.0 * settings.acquisition.sample_period_s),
        unit_id=m.unit,
        now=clock,
    )
    can_sensor = CanSpindleSensor(
        interface=c.interface,
        channel=c.channel,
        bitrate=c.bitrate,
        fd=c.fd,
        data_bitrate=c.data_bitrate,
        can_filters=None if c.filters is None else [f.model_dump(exclude_none=True) for f in c.filters],
        bus_kwargs=dict(c.options),
        dbc=c.dbc,
        stale_after_s=c.stale_after_s,
        batch_s=c.batch_s,
        now=clock,
    )
    return daq, can_sensor


def until_signal() -> asyncio.Event:
    """An event set on SIGINT or SIGTERM, the stop of ``serve`` and ``serve_host`` (handlers on the running
    loop; where it cannot take them, e.g. outside the main thread, only the caller sets it)."""
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        with contextlib.suppress(NotImplementedError, RuntimeError):
            loop.add_signal_handler(sig, stop.set)
    return stop


async def serve(settings: Settings, *, migrate: bool) -> int:
    from service.host.runtime import Runtime, ScaledClock

    if settings.spindles:
        return await serve_host(settings, migrate=migrate)
    clock = ScaledClock(1.0)
    runtime = Runtime(settings=settings, clock=clock, migrate=migrate, on_event=lambda m: log.info("%s", m))
    log.info("loading the model (cache %s)", settings.model.rom_cache_dir)
    await asyncio.to_thread(runtime.load, progress=lambda m: log.info("%s", m))
    daq, can_sensor = make_device_drivers(settings, clock=clock)
    stop = until_signal()
    try:
        await runtime.start(daq=daq, can=can_sensor, api=True)
        await runtime.wait_api()
        log.info("%s", freeze_startup_heap().message())
        log.info("serving on %s", runtime.url)
        await stop.wait()
    finally:
        await runtime.stop()
    log.info("stopped")
    return 0


async def serve_host(settings: Settings, *, migrate: bool) -> int:
    """Several spindles (``[[spindles]]``) in this one process: ``service.host.fleet``."""
    from service.host.fleet import Host
    from service.host.runtime import ScaledClock

    clock = ScaledClock(1.0)
    host = Host(
        settings=settings,
        clock=clock,
        devices=lambda s: make_device_drivers(s, clock=clock),
        migrate=migrate,
        on_event=lambda m: log.info("%s", m),
    )
    log.info("hosting %d spindles (model cache %s)", len(settings.spindles), settings.model.rom_cache_dir)
    stop = until_signal()
    try:
        await host.start(api=True)
        await host.wait_api()
        log.info("%s", freeze_startup_heap().message())
        log.info(
            "serving %d spindles on %s (list: %sapi/v1/spindles)", len(host.spindles), host.url, host.url
        )
        await stop.wait()
    finally:
        await host.stop()
    log.info("stopped")
    return 0


def migrates_by_default(url: str) -> bool:
    """True for SQLite: its file belongs to this one service, so its schema is created and upgraded at start.

    A PostgreSQL schema may be shared (several spindles, readers, a DBA's role without DDL rights) and is
    upgraded only by ``--migrate`` or the Alembic CLI, after a backup (deploy/OPERATIONS.md, "Upgrades").
    """
    from sqlalchemy.engine import make_url

    return make_url(url).get_backend_name() == "sqlite"


def main(args: argparse.Namespace) -> int:
    import json

    from drivers.errors import ConfigError
    from service.commands.demo import log_spindle_default, quiet_third_party_logs
    from service.host.fleet import HostError
    from service.serve.errors import OutletError
    from service.serve.opcua.preflight import check_opcua_files
    from service.settings import SettingsError, load_settings

    quiet_third_party_logs()
    logging.getLogger("chtc").setLevel(logging.INFO)
    logging.getLogger("service").setLevel(logging.INFO)
    try:
        settings = load_settings(args.config)
        api = {k: v for k, v in (("host", args.host), ("port", args.port)) if v is not None}
        settings = override(settings, "api", **api) if api else settings
    except (SettingsError, CommandError) as err:
        print(f"chtc run: {err}", file=sys.stderr)
        return 2
    log_spindle_default(settings)
    if args.print_config:
        print(json.dumps(settings.redacted(), indent=2))
        return 0
    try:
        check_database_url(settings.database.url, "database.url")
        check_listens(settings)
        if settings.opcua.enabled:  # an unreadable certificate: one line before the model loads
            check_opcua_files(settings.opcua)
        migrate = args.migrate or migrates_by_default(settings.database.url)
        return asyncio.run(serve(settings, migrate=migrate))
    except (ConfigError, CommandError, HostError, OutletError) as err:
        print(f"chtc run: {err}", file=sys.stderr)
        return 2
