"""The ``chtc`` command line as a newcomer meets it: defaults in ``--help``, one-line errors, port checks."""

from __future__ import annotations

import argparse
import socket
from collections.abc import Callable, Sequence

import pytest

from benchmarks import cli as bench_cli
from service.cli import COMMANDS, build_parser, main


def _subparser(
    argv: list[str], build: Callable[[Sequence[str]], argparse.ArgumentParser] = build_parser
) -> argparse.ArgumentParser:
    parser = build(argv)
    action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    sub: argparse.ArgumentParser = action.choices[argv[0]]
    return sub


ALL = [[c] for c in COMMANDS] + [["benchmarks", b] for b in bench_cli.BENCHMARKS]  # python -m benchmarks


@pytest.mark.parametrize("argv", ALL, ids=" ".join)
def test_help_states_every_default(argv: list[str]) -> None:
    """Every option that takes a value says its default (or what happens without it) in ``--help``."""
    sub = _subparser(argv[1:], bench_cli.build_parser) if argv[0] == "benchmarks" else _subparser(argv)
    formatter = sub._get_formatter()
    missing = []
    for action in sub._actions:
        if not action.option_strings or action.nargs == 0 or action.required:
            continue
        text = formatter._expand_help(action) if action.help else ""
        if "default" not in text.lower():
            missing.append(action.option_strings[-1])
    assert not missing, f"chtc {' '.join(argv)}: no default in --help for {missing}"


def test_chtc_lists_product_commands_only(capsys: pytest.CaptureFixture[str]) -> None:
    """The operator's ``chtc --help`` names the product's commands; the benchmarks are
    ``python -m benchmarks`` (issue 39), and ``chtc bench`` is no command."""
    with pytest.raises(SystemExit):
        main(["--help"])
    out = capsys.readouterr().out
    assert all(c in out for c in COMMANDS) and "bench" not in out
    with pytest.raises(SystemExit) as exc:
        main(["bench", "compensation"])
    assert exc.value.code == 2 and "invalid choice: 'bench'" in capsys.readouterr().err


def test_help_shows_the_demo_port_and_simulate_speedup(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        main(["demo", "--help"])
    assert "(default: 8000)" in " ".join(capsys.readouterr().out.split())
    with pytest.raises(SystemExit):
        main(["simulate", "--help"])
    assert "(default: 1.0)" in " ".join(capsys.readouterr().out.split())


def test_run_and_replay_take_host_and_port() -> None:
    args = build_parser(["run"]).parse_args(["run", "--host", "0.0.0.0", "--port", "8123"])
    assert (args.host, args.port) == ("0.0.0.0", 8123)
    args = build_parser(["replay"]).parse_args(["replay", "x.csv", "--api", "--port", "8124"])
    assert (args.api, args.port) == (True, 8124)


def _demo_error(argv: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    with pytest.raises(SystemExit) as exc:  # argparse errors exit; the others return 2
        raise SystemExit(main(["demo", *argv, "--duration", "0"]))
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return err


@pytest.mark.parametrize(
    ("name", "content", "expected"),
    [
        ("syntax.toml", "x = \n", "invalid TOML"),
        ("typo.toml", "[apii]\nport = 1\n", "apii: unknown key"),
    ],
)
def test_demo_bad_config_is_one_clear_line(tmp_path, capsys, name, content, expected) -> None:
    path = tmp_path / name
    path.write_text(content)
    assert expected in _demo_error(["--config", str(path)], capsys)


def test_demo_missing_config_garbage_url_and_bad_port(tmp_path, capsys) -> None:
    assert "cannot read config file" in _demo_error(["--config", str(tmp_path / "none.toml")], capsys)
    assert "database.url" in _demo_error(["--database-url", "garbage"], capsys)
    assert "70000 is not a TCP port" in _demo_error(["--port", "70000"], capsys)


@pytest.mark.parametrize("command", ["demo", "run"])
def test_busy_port_is_reported_before_the_model_loads(command, capsys, monkeypatch) -> None:
    """The port check comes first: a model load would fail the test (it is replaced by an error)."""
    import service.modelload as modelload

    def no_load(*a: object, **k: object) -> None:
        raise AssertionError("the model was loaded before the port was checked")

    monkeypatch.setattr(modelload, "load_model", no_load)
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen(1)
        port = busy.getsockname()[1]
        assert main([command, "--port", str(port)]) == 2
    err = capsys.readouterr().err
    assert f"cannot listen on 127.0.0.1:{port}" in err and "Traceback" not in err
