"""What only the command line uses: the `mures` CLI, the paper's experiments and the report, the
Fig. 4 toy, the fleet simulator and its world. May import every other part of shared/."""

import sys


def mures_main() -> int:
    """The `mures` entry point: a clear error when the install lacks an extra the CLI needs."""
    try:
        from shared.tools.cli import main
    except ModuleNotFoundError as exc:
        print(
            f"mures: error: this install lacks {exc.name!r}; `mures` needs the trainer: "
            "pip install 'mures-fleet[all]' (a robot computer needs only `robot-agent`)",
            file=sys.stderr,
        )
        return 2
    return main()
