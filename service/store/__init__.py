"""Persistence: SQLAlchemy 2.0 models, repository, buffered writer, Alembic migrations.

Everything is built at the edge from ``settings.database``; nothing connects at import. API::

    from service.contracts import records         # the plain records (below the store, shared)
    from service.store import engine, migrate, repository as repo, writer
    from service.serve.views import row_to_record  # the serving side (the store imports no serve/engine)

    eng = engine.create_db_engine(settings.database.url, echo=settings.database.echo)  # SQLite: WAL, FKs on
    migrate.upgrade(eng)                       # or URL; to "head"; current_revision(eng), head_revision()
    factory = engine.make_session_factory(eng, spindle_id="spindle1")  # sessions see this spindle's rows only
    with repo.session_scope(factory) as s:     # the service registers its spindle at start-up
        repo.ensure_spindle(s, "spindle1", description="", now=datetime.now(UTC))

    # one session per job/request; SQLAlchemy errors → DatabaseUnavailableError / RecordError
    with repo.session_scope(factory, "list identifications") as s:
        page = repo.list_identifications(s, since=t0, until=t1, limit=50, offset=0, outcome=None)
        row = repo.get_identification(s, 12)              # RecordNotFoundError if absent
        data = records.IdentificationData.from_row(row)   # the stored record back (inverse of values())
        rec = row_to_record(row)                          # -> contracts.snapshots.IdentificationRecord
        last = repo.last_identification(s)                # newest "ok" one, or None if there is none
        seeds = repo.latest_per_condition(s, limit=100)   # newest ok result per condition (scheduler history)
        max_cond_id, max_ident_id = repo.max_ids(s)       # resume id counters after a restart
        repo.list_conditions(s, since=..., until=..., limit=..., offset=...)        # Page[Condition]
        repo.list_device_events(s, since=..., until=..., device="modbus", limit=100)  # Page[DeviceEvent]
        repo.list_samples(s, since=..., until=..., limit=10_000)          # list[SampleRow], oldest 1st
        repo.add_condition / end_condition / add_identification / add_device_event / add_samples(s, record(s))
        repo.write_records(s, [record, ...])              # what the writer does per batch

    # the service's write path: never blocks, buffers while the database is down, retries with backoff
    w = writer.DbWriter(factory, batch_size=500, buffer_max=100_000, retry_initial_s=0.5, retry_max_s=30.0,
                        clock=lambda: datetime.now(UTC)).start()
    w.submit(records.ConditionStart(id=7, started_at=t, speed_rpm=4000.0, torque_nm=10.0, ambient_c=22.0))
    w.submit(records.ConditionEnd(id=6, ended_at=t))
    w.submit(records.IdentificationData.from_result(result, id=12, condition_id=7, started_at=..,
             finished_at=.., window_start=.., window_end=.., reason="schedule", model_version="...",
             warm_start_source="condition 6", warm_start_id=11))
    # or IdentificationData(...) directly, with outcome="failed"/"skipped"/"cancelled"/... and a message
    w.submit(records.SampleData(t=t, temps_c=temps, ambient_c=22.0, speed_rpm=4000.0, torque_nm=10.0,
                                quality=("ok",) * 32))   # quality: drivers.quality.Quality labels
    w.submit(records.DeviceEventData(t=t, device="modbus", kind="timeout", detail="unit 1, 1.0 s"))
    w.status()   # WriterStatus(connected, pending, written, dropped, rejected, errors, lost_on_close,
                 #              last_error, last_error_at, last_ok_at)  -> health / metrics
    w.flush(timeout_s=10.0) -> bool ; w.close(timeout_s=10.0) -> WriterStatus   # on shutdown

    # many spindles in one database (docs/design/persistence.md): rows stamped and filtered by spindle;
    retention.retention_pass(eng, now=now, raw_days=30, minute_days=365)  # -> RetentionReport (all spindles)
    merge.merge("sqlite:///old.db", eng, spindle_id="cell3-s07")            # a one-spindle database in

Ids of conditions and identifications are assigned by the service (start from ``repo.max_ids`` + 1; if the
database is down at start, any larger unique integers, e.g. epoch milliseconds, work): the writer may hold
the rows for a while, and the API needs the id at once. All datetimes are aware UTC (naive ones are refused).
Errors: see ``service.store.errors`` (SQLAlchemy errors are translated in ``service.store.sqlerrors``).
"""
