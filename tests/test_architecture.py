"""The rooms of docs/architecture.md hold: who may import whom (lazy imports inside functions
included), no import circle anywhere, and a robot agent that never loads torch."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("shared", "robot_agent", "training_server")

# room -> the project rooms it may import (a room is a module-name prefix)
ALLOWED: dict[str, tuple[str, ...]] = {
    "shared.core": ("shared.core",),
    "shared.engine": ("shared.core", "shared.engine"),
    "shared.envs": ("shared.core", "shared.engine", "shared.envs"),
    "shared.learning": ("shared.core", "shared.engine", "shared.envs", "shared.learning"),
    "shared.planners": ("shared.core", "shared.engine", "shared.planners"),
    "shared.registry": ("shared.core", "shared.engine", "shared.planners", "shared.learning", "shared.registry"),
    "shared.floorplan": ("shared.core", "shared.floorplan"),
    "shared.world": ("shared.core", "shared.floorplan", "shared.world"),
    "shared.tools": ("shared",),
    "robot_agent": ("shared.core", "robot_agent"),
    "training_server": ("shared.core", "shared.engine", "shared.learning", "shared.floorplan", "training_server"),
}
HEAVY = ("torch", "scipy", "matplotlib", "fastapi", "starlette", "uvicorn", "pydantic")
FORBIDDEN: dict[str, tuple[str, ...]] = {
    "shared.core": HEAVY,
    "robot_agent": HEAVY,
    "shared.engine": ("scipy", "matplotlib", "fastapi", "torchrl", "tensordict", "pettingzoo"),
    "shared.envs": ("scipy", "matplotlib", "fastapi"),
    "shared.learning": ("scipy", "matplotlib", "fastapi"),
    "shared.planners": ("matplotlib", "fastapi"),
    "shared.floorplan": ("torch", "matplotlib", "fastapi"),
    "shared.world": ("torch", "matplotlib", "fastapi"),
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


@pytest.mark.slow
def test_the_core_install_runs_an_agent_decision_without_torch(tmp_path):
    """`pip install .` (no extras) into a fresh venv: no torch, scipy, matplotlib or fastapi; the
    agent starts, the trainer's command says which extra it needs, and a snapshot written by the
    trainer is read and decided on with numpy alone, the same moves as in this environment."""
    import torch

    from shared.core.graph import builtin_graph
    from shared.core.models import Sensor, identity_model
    from shared.core.snapshot_format import PolicyAgent, read_snapshot
    from shared.learning.policy import TeamPolicy
    from shared.learning.team_snapshot import save_snapshot

    venv = tmp_path / "core"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
    py = venv / "bin" / "python"
    pip = [str(py), "-m", "pip", "install", "-q", "-c", str(ROOT / "constraints.txt"), str(ROOT)]
    subprocess.run(pip, check=True, capture_output=True, text=True)
    listed = subprocess.run([str(py), "-m", "pip", "list"], capture_output=True, text=True, check=True).stdout
    assert not [m for m in HEAVY if m in listed.lower()], listed
    assert subprocess.run([str(venv / "bin" / "robot-agent"), "--help"], capture_output=True).returncode == 0
    r = subprocess.run([str(venv / "bin" / "mures"), "map", "--env", "office"], capture_output=True, text=True)
    assert r.returncode == 2 and "mures-fleet[all]" in r.stderr
    g = builtin_graph("office")
    torch.manual_seed(3)
    pol = TeamPolicy(g.n, 2, torch.as_tensor(g.adjacency()))
    snap = save_snapshot(tmp_path / "snap", pol, g, identity_model(g), Sensor(), "cepg", [0.5, 0.5], {}, {})
    code = (
        "import sys\n"
        "from shared.core.graph import builtin_graph\n"
        "from shared.core.snapshot_format import PolicyAgent, read_snapshot\n"
        "g = builtin_graph('office'); a = PolicyAgent(read_snapshot(sys.argv[1], g), g, 1, seed=7)\n"
        "p = g.start; a.reset(p, 0); moves = []\n"
        "for t in range(30):\n"
        "    p = a.act(p); moves.append(p); a.observe(p, 0)\n"
        "print(moves)"
    )
    out = subprocess.run([str(py), "-c", code, str(snap)], capture_output=True, text=True, check=True, cwd=tmp_path)
    here = PolicyAgent(read_snapshot(snap, g), g, 1, seed=7)
    p = g.start
    here.reset(p, 0)
    moves = []
    for _ in range(30):
        p = here.act(p)
        moves.append(p)
        here.observe(p, 0)
    assert out.stdout.strip() == str(moves)
