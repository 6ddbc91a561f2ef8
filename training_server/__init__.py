"""The central training server: episode ingest over Zenoh, storage, the REST API, training runs
(EM, CE-PG, the evaluation gate) and versioned policies (docs/architecture.md)."""

import sys


def main() -> int:
    """The `training-server` entry point: a clear error when the install lacks the server extra."""
    try:
        from training_server.cli import main as server_main
    except ModuleNotFoundError as exc:
        print(
            f"training-server: error: this install lacks {exc.name!r}: pip install 'mures-fleet[server]'",
            file=sys.stderr,
        )
        return 2
    return server_main()
