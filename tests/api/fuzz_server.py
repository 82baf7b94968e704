"""The API over the in-memory demo service for the schemathesis acceptance runs (docs/api.md, "Fuzzing").

``python -m tests.api.fuzz_server PORT [--read-token]`` serves on 127.0.0.1:PORT with the production uvicorn
limits (``api.server.server_config``). The service's clock is frozen at start so the data stay fresh (readyz
200) however long the run. Tokens: write ``fuzz-write-token-0123456789``, read (with ``--read-token``)
``fuzz-read-token-0123456789``.
"""

from __future__ import annotations

import argparse
from datetime import UTC, datetime

import uvicorn

from api.app import create_app
from api.server import server_config
from service.serve.interface_memory import demo_service
from service.settings import Settings

WRITE_TOKEN = "fuzz-write-token-0123456789"
READ_TOKEN = "fuzz-read-token-0123456789"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("port", type=int)
    parser.add_argument("--read-token", action="store_true", help=f"also require {READ_TOKEN!r} for reads")
    args = parser.parse_args()
    api = {"token": WRITE_TOKEN} | ({"read_token": READ_TOKEN} if args.read_token else {})
    start = datetime.now(UTC)
    app = create_app(Settings(api=api), demo_service(clock=lambda: start), clock=lambda: start)
    uvicorn.Server(server_config(app, host="127.0.0.1", port=args.port)).run()


if __name__ == "__main__":
    main()
