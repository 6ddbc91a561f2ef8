"""The rooms of docs/architecture.md hold: who may import whom (lazy imports inside functions
included), no import circle anywhere, and a robot agent that never loads torch."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("shared", "robot_agent", "training_server")

# room -> the project rooms it may import (a room is a module-name prefix)
ALLOWED: dict[str, tuple[str, ...]] = {
    "shared.core": ("shared.core",),
    "shared.engine": ("shared.core", "shared.engine"),
    "shared.learning": ("shared.core", "shared.engine", "shared.learning"),
    "shared.planners": ("shared.core", "shared.engine", "shared.planners"),
    "shared.registry": ("shared.core", "shared.engine", "shared.planners", "shared.learning", "shared.registry"),
    "shared.tools": ("shared",),
    "robot_agent": ("shared.core", "robot_agent"),
    "training_server": ("shared.core", "shared.engine", "shared.learning", "training_server"),
}
HEAVY = ("torch", "scipy", "matplotlib", "fastapi", "starlette", "uvicorn", "pydantic")
FORBIDDEN: dict[str, tuple[str, ...]] = {
    "shared.core": HEAVY,
    "robot_agent": HEAVY,
    "shared.engine": ("scipy", "matplotlib", "fastapi"),
    "shared.learning": ("scipy", "matplotlib", "fastapi"),
    "shared.planners": ("matplotlib", "fastapi"),
}


def _modules() -> dict[str, Path]:
    out = {}
    for pkg in PACKAGES:
        for p in (ROOT / pkg).rglob("*.py"):
            parts = list(p.relative_to(ROOT).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join(parts)] = p
    return out


def _imports(path: Path, module: str) -> set[str]:
    """Every module ``module`` imports, at the top or inside functions."""
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module:
            base = node.module
            if node.level:  # relative import
                base = ".".join([*module.split(".")[: -node.level], node.module])
            found.add(base)
            found.update(f"{base}.{a.name}" for a in node.names)
    return found


def _room(module: str, rooms: tuple[str, ...]) -> str | None:
    hits = [r for r in rooms if module == r or module.startswith(r + ".")]
    return max(hits, key=len) if hits else None


def _graph() -> dict[str, set[str]]:
    mods = _modules()
    return {m: {i for i in _imports(p, m) if i in mods and i != m} for m, p in mods.items()}


def test_every_module_lives_in_a_room():
    homeless = [m for m in _modules() if m not in PACKAGES and m != "shared" and _room(m, tuple(ALLOWED)) is None]
    assert not homeless, f"modules outside the rooms of docs/architecture.md: {homeless}"


def test_rooms_import_only_what_they_may():
    mods = _modules()
    bad = []
    for m, p in mods.items():
        room = _room(m, tuple(ALLOWED))
        if room is None:
            continue
        for imp in _imports(p, m):
            top = imp.split(".")[0]
            if top in PACKAGES and imp in mods and _room(imp, ALLOWED[room]) is None and imp not in PACKAGES:
                bad.append(f"{m} imports {imp}")
            forbidden = FORBIDDEN.get(_room(m, tuple(FORBIDDEN)) or "", ())
            if top in forbidden:
                bad.append(f"{m} imports {top}")
    assert not bad, "\n".join(bad)


def test_no_import_circle():
    graph = _graph()
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(m: str) -> list[str] | None:
        state[m] = 1
        stack.append(m)
        for d in sorted(graph[m]):
            if state.get(d) == 1:
                return [*stack[stack.index(d) :], d]
            if d not in state and (cycle := visit(d)):
                return cycle
        stack.pop()
        state[m] = 2
        return None

    for m in sorted(graph):
        if m not in state:
            cycle = visit(m)
            assert cycle is None, " -> ".join(cycle)


def test_the_agent_process_imports_no_heavy_library():
    code = (
        "import sys, robot_agent.agent, robot_agent.backend, robot_agent.examples.nav_goal\n"
        f"print(sorted(m for m in {HEAVY!r} if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT)
    assert out.stdout.strip() == "[]", out.stdout
