"""The command-line reference and the REST API reference, generated from the programs' own argparse
parsers and the server's OpenAPI document, so that they cannot drift from the code. A page asks
for one with a marker line; what follows it, up to the end marker, is the generated text:

    <!-- generated: command-line -->
    <!-- generated: rest-api -->
    ...
    <!-- end of generated text -->

The text is kept in the page, so that docs/cli.md and docs/api.md read as plain Markdown;
`make reference` (this file run as a script) writes it anew, tests/test_docs.py checks it is
current, and as an MkDocs hook it fills the site's pages at build time.
"""

from __future__ import annotations

import argparse
import os
from types import SimpleNamespace
from typing import Any

CLI = "<!-- generated: command-line -->"
API = "<!-- generated: rest-api -->"
END = "<!-- end of generated text -->"
PAGES = {"cli.md": CLI, "api.md": API}


def _help(parser: argparse.ArgumentParser) -> str:
    return "```text\n" + parser.format_help().rstrip() + "\n```\n"


def _subcommands(prefix: str, parser: argparse.ArgumentParser) -> list[str]:
    """A section for every subcommand of ``parser``, and theirs (`mures map import`)."""
    out = []
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                out.append(f"### {prefix} {name}\n\n" + _help(sub))
                out += _subcommands(f"{prefix} {name}", sub)
    return out


def command_line() -> str:
    from robot_agent.agent import build_parser as agent_parser
    from shared.tools.cli import build_parser as mures_parser
    from training_server.cli import build_parser as server_parser
    from training_server.kit import build_parser as kit_parser

    os.environ["COLUMNS"] = "100"  # argparse wraps to the terminal: one width for the page
    out = []
    mures = mures_parser()
    out.append("## mures\n\n" + _help(mures))
    out += _subcommands("mures", mures)
    out.append("## training-server\n\n" + _help(server_parser()))
    out.append("### training-server kit\n\n" + _help(kit_parser()))
    out.append("## robot-agent\n\n" + _help(agent_parser()))
    return "\n".join(out)


def rest_api() -> str:
    from training_server.api import create_app

    spec = create_app(SimpleNamespace()).openapi()
    out = [f"OpenAPI {spec['openapi']}, {spec['info']['title']} version {spec['info']['version']}.\n"]
    out.append("| method | path | what it does | statuses |\n| --- | --- | --- | --- |")
    for path, ops in sorted(spec["paths"].items()):
        for method, op in ops.items():
            what = (op.get("summary") or "").replace("|", "\\|")
            doc = (op.get("description") or "").split("\n\n")[0].replace("\n", " ").replace("|", "\\|")
            statuses = ", ".join(sorted(op.get("responses", {})))
            out.append(f"| {method.upper()} | `{path}` | {doc or what} | {statuses} |")
    out.append("\n" + training_hyperparameters())
    return "\n".join(out) + "\n"


def training_hyperparameters() -> str:
    """`POST /api/v1/training-runs`' ``hyperparameters``: each MARL method's names and defaults."""
    from shared.learning.marl import MARL_ALGORITHMS, hyperparameters

    out = [
        "### Hyperparameters of a training run",
        "",
        "`POST /api/v1/training-runs` takes `hyperparameters` as `{method: {name: value}}`, for example",
        '`{"algorithm": "mappo", "hyperparameters": {"mappo": {"lr": 0.0003, "envs": 64}}}`; a name a method',
        "does not have, or a value of the wrong type, fails the run at once, naming it. CE-PG and PG take",
        "the run's own fields (`beta`, `lr`, `variant`). Each method's names, with their defaults:",
        "",
        "| method | hyperparameters (defaults) |",
        "| --- | --- |",
    ]
    for name in MARL_ALGORITHMS:
        pairs = ", ".join(f"`{k}` {v}" for k, v in hyperparameters(name).to_dict().items())
        out.append(f"| {name} | {pairs} |")
    return "\n".join(out) + "\n"


def filled(markdown: str) -> str:
    """``markdown`` with the text after each marker (up to END, or none yet) generated anew."""
    for marker, make in ((CLI, command_line), (API, rest_api)):
        if marker not in markdown:
            continue
        head, _, rest = markdown.partition(marker)
        _old, found, tail = rest.partition(END)
        markdown = head + marker + "\n\n" + make().rstrip() + "\n\n" + END + (tail if found else "\n")
    return markdown


def on_page_markdown(markdown: str, page: Any, config: Any, files: Any) -> str:
    return _results_links(filled(markdown), page)


# docs/results.md is written by `mures report` and links its figures where they live, in
# results/ beside docs/ (../results/figN/figN.png); the site serves them from results-figures/.
RESULTS_LINK = "](../results/"
RESULTS_SITE = "results-figures"


def on_files(files: Any, config: Any) -> Any:
    from pathlib import Path

    from mkdocs.structure.files import File

    root = Path(config["docs_dir"]).resolve().parent
    for png in sorted((root / "results").glob("*/*.png")):
        rel = png.relative_to(root / "results").as_posix()
        files.append(File.generated(config, f"{RESULTS_SITE}/{rel}", abs_src_path=str(png)))
    return files


def _results_links(markdown: str, page: Any) -> str:
    if page.file.src_uri == "results.md":
        markdown = markdown.replace(RESULTS_LINK, f"]({RESULTS_SITE}/")
    return markdown


if __name__ == "__main__":  # make reference: write the generated text into docs/cli.md and docs/api.md
    from pathlib import Path

    for page in PAGES:
        path = Path(__file__).resolve().parent.parent / page
        path.write_text(filled(path.read_text(encoding="utf-8")), encoding="utf-8")
        print(f"wrote {path}")
