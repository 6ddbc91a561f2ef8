"""MkDocs hook: the command-line reference and the REST API reference, generated at build time from
the programs' own argparse parsers and the server's OpenAPI document, so that they cannot drift
from the code. A page asks for one with a marker line:

    <!-- generated: command-line -->
    <!-- generated: rest-api -->
"""

from __future__ import annotations

import argparse
import os
from types import SimpleNamespace
from typing import Any

CLI = "<!-- generated: command-line -->"
API = "<!-- generated: rest-api -->"


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
    return "\n".join(out) + "\n"


def on_page_markdown(markdown: str, page: Any, config: Any, files: Any) -> str:
    if CLI in markdown:
        markdown = markdown.replace(CLI, command_line())
    if API in markdown:
        markdown = markdown.replace(API, rest_api())
    return _results_links(markdown, page)


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
