"""The API over the real service for the schemathesis acceptance runs (docs/design/api.md, "Fuzzing").

``python -m tests.api.fuzz_server PORT [--read-token]`` serves on 127.0.0.1:PORT with the production uvicorn
limits (``api.server.server_config``) the real service (``simulator.served``: the core and the shell on
SQLite in a temporary directory, fed the demo plan's first 22 min of virtual-plant samples). No more samples
follow and the service's clock stays at the last one, so the data stay fresh (readyz 200) however long the
run; the fuzzer's POSTs start real identifications. Tokens: write ``fuzz-write-token-0123456789``, read (with
``--read-token``) ``fuzz-read-token-0123456789``.
"""

from __future__ import annotations

import argparse
import tempfile

import uvicorn

from api.app import create_app
from api.server import server_config
from service.settings import Settings
from simulator.served import DEMO_FED, exit_on_sigterm, served_service

WRITE_TOKEN = "fuzz-write-token-0123456789"
READ_TOKEN = "fuzz-read-token-0123456789"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("port", type=int)
    parser.add_argument("--read-token", action="store_true", help=f"also require {READ_TOKEN!r} for reads")
    args = parser.parse_args()
    api = {"token": WRITE_TOKEN} | ({"read_token": READ_TOKEN} if args.read_token else {})
    exit_on_sigterm()
    with (
        tempfile.TemporaryDirectory(prefix="chtc-fuzz-") as tmp,
        served_service(database_url=f"sqlite:///{tmp}/chtc.db", feed_samples=DEMO_FED) as served,
    ):
        app = create_app(Settings(api=api), served.service, clock=served.clock)
        uvicorn.Server(server_config(app, host="127.0.0.1", port=args.port)).run()


if __name__ == "__main__":
    main()
