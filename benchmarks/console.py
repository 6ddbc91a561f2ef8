"""The operator console's figures: server time to render each page, and the live view with 20
robots moving (update rate, browser CPU); with --screenshots, the main views of a real fleet-sim
saved as PNG for the docs.

    python benchmarks/console.py [--robots 20] [--seconds 30] [--out FILE] [--screenshots DIR [--no-figures]]

Live view: a training-server on loopback and ROBOTS synthetic robots (a fleet-sim of 20 agent
processes is too heavy for 2 cores): each declares its liveliness token like an agent and publishes
telemetry at the agents' rate (5 Hz) with a random walk on OFFICE and a belief of n floats; all fly
one mission started through the API. Chromium (Playwright) shows the fleet page with one robot's
belief selected, for SECONDS. Reported: fleet and belief events the page received per second,
robot-marker moves per second, the page's main-thread busy time (CDP Performance TaskDuration)
and the CPU time of all Chromium processes, both as a fraction of one core; once as the page
opens, once with "glide between rooms" (CSS transitions of the markers) on.

Render time: every page GET 50 times; the server's own template time (its Server-Timing header)
and the whole response time seen by the client, medians.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import sys
import tempfile
import threading
import time
import urllib.request
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from shared.core.files import read_token
from shared.core.graph import builtin_graph
from shared.core.models import Sensor, uniform_walk
from shared.core.wire import agent_key, telemetry_key, zenoh_config
from shared.tools.fleetsim import launch, start_server

PAGES = ["/", "/missions", "/policies", "/training", "/data", "/signin", "/missions/m-1"]


def chromium() -> str:
    exe = os.environ.get("MURES_CHROMIUM") or shutil.which("chromium")
    if exe is None:
        raise SystemExit("no chromium on PATH (apt-get install chromium)")
    return exe


def render_times(base: str, repeats: int = 50) -> dict[str, dict[str, float]]:
    out = {}
    for path in PAGES:
        server, client = [], []
        for _ in range(repeats):
            t0 = time.perf_counter()
            with urllib.request.urlopen(base + path) as r:
                r.read()
                timing = r.headers["Server-Timing"]
            client.append((time.perf_counter() - t0) * 1e3)
            server.append(float(timing.split("dur=")[1]))
        out[path] = {
            "render_ms": round(statistics.median(server), 3),
            "response_ms": round(statistics.median(client), 2),
        }
    return out


class SyntheticRobots:
    """ROBOTS robots on Zenoh as agents look to the server: liveliness tokens and 5 Hz telemetry."""

    def __init__(self, endpoint: str, fleet: str, graph, robots: int, seed: int = 0) -> None:
        import zenoh

        self.graph = graph
        self.ids = [f"s{i + 1:02d}" for i in range(robots)]
        self.session = zenoh.open(zenoh_config("client", connect=[endpoint]))
        self.tokens = [self.session.liveliness().declare_token(agent_key(fleet, r)) for r in self.ids]
        self.pubs = {r: self.session.declare_publisher(telemetry_key(fleet, r)) for r in self.ids}
        self.rng = np.random.default_rng(seed)
        self.node = {r: int(graph.start) for r in self.ids}
        self.mission: str | None = None
        self.t = 0
        self.sent = 0
        self.running = True
        self.thread = threading.Thread(target=self._loop, daemon=True)
        self.thread.start()

    def _loop(self) -> None:
        g = self.graph
        while self.running:
            t0 = time.perf_counter()
            for r in self.ids:
                self.node[r] = int(self.rng.choice(g.closed(self.node[r])))
                belief = self.rng.dirichlet(np.full(g.n, 0.3))
                msg = {
                    "state": "idle",
                    "node": int(g.labels[self.node[r]]),
                    "policy_version": 1,
                    "backend": "synthetic",
                }
                if self.mission:
                    msg = {
                        **msg,
                        "state": "mission",
                        "mission_id": self.mission,
                        "t": self.t,
                        "z": int(self.rng.random() < 0.05),
                        "belief": [round(float(x), 4) for x in belief],
                    }
                msg["ts"] = round(time.time(), 3)
                self.pubs[r].put(json.dumps(msg).encode())
                self.sent += 1
            self.t += 1
            time.sleep(max(0.0, 0.2 - (time.perf_counter() - t0)))  # 5 Hz, the agents' rate

    def close(self) -> None:
        self.running = False
        self.thread.join(2)
        for x in [*self.pubs.values(), *self.tokens]:
            x.undeclare()
        self.session.close()


def chromium_cpu_s() -> float:
    """User + system CPU seconds of every Chromium process now running."""
    total = 0.0
    tick = os.sysconf("SC_CLK_TCK")
    for pid in filter(str.isdigit, os.listdir("/proc")):
        try:
            cmd = Path(f"/proc/{pid}/cmdline").read_bytes()
            if b"chromium" not in cmd:
                continue
            fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
            total += (int(fields[11]) + int(fields[12])) / tick
        except (OSError, IndexError, ValueError):
            continue
    return total


def live_view(base: str, token: str, robots: SyntheticRobots, seconds: float, animate: bool) -> dict[str, float]:
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=chromium())
        page = browser.new_page(viewport={"width": 1400, "height": 900})
        page.goto(base + "/signin")
        page.get_by_label("Token").fill(token)
        page.get_by_role("button", name="Sign in").click()
        page.wait_for_selector("body[data-ready='1']")
        page.wait_for_selector(f"#fleet-table tr[data-robot='{robots.ids[0]}']")
        page.locator(f"#fleet-table tr[data-robot='{robots.ids[0]}'] td").first.click()
        page.wait_for_selector(f"svg#map g.robot[data-robot='{robots.ids[-1]}']")
        if animate:
            page.check("#animate")
        page.evaluate(
            """() => { window.moves = 0; new MutationObserver((ms) => { for (const m of ms)
              if (m.target.classList && m.target.classList.contains('robot') && m.attributeName === 'style') window.moves++; })
              .observe(document.querySelector('svg#map'), {subtree: true, attributes: true}); }"""
        )
        cdp = page.context.new_cdp_session(page)
        cdp.send("Performance.enable")
        time.sleep(2)  # settle

        def task_s() -> float:
            return next(
                m["value"] for m in cdp.send("Performance.getMetrics")["metrics"] if m["name"] == "TaskDuration"
            )

        stats0, moves0, task0, cpu0, sent0 = (
            page.evaluate("() => ({...window.muresStats})"),
            page.evaluate("() => window.moves"),
            task_s(),
            chromium_cpu_s(),
            robots.sent,
        )
        t0 = time.perf_counter()
        time.sleep(seconds)
        wall = time.perf_counter() - t0
        stats1, moves1, task1, cpu1, sent1 = (
            page.evaluate("() => ({...window.muresStats})"),
            page.evaluate("() => window.moves"),
            task_s(),
            chromium_cpu_s(),
            robots.sent,
        )
        drawn = page.locator("svg#map g.robot").count()
        browser.close()
    return {
        "glide_between_rooms": animate,
        "robots": len(robots.ids),
        "robots_drawn": drawn,
        "seconds": round(wall, 1),
        "telemetry_messages_per_s": round((sent1 - sent0) / wall, 1),
        "fleet_events_per_s": round((stats1.get("fleet", 0) - stats0.get("fleet", 0)) / wall, 2),
        "belief_events_per_s": round((stats1.get("belief", 0) - stats0.get("belief", 0)) / wall, 2),
        "robot_marker_moves_per_s": round((moves1 - moves0) / wall, 1),
        "page_main_thread_busy": round((task1 - task0) / wall, 4),
        "chromium_cpu_cores": round((cpu1 - cpu0) / wall, 4),
    }


def figures(args: argparse.Namespace) -> dict:
    graph = builtin_graph("office")
    with tempfile.TemporaryDirectory(prefix="mures-console-") as tmp:
        logs = Path(tmp) / "logs"
        logs.mkdir()
        data = Path(tmp) / "data"
        proc, base, endpoint = start_server(["--env", "office"], data, 4, Sensor(), logs)
        robots = None
        try:
            out: dict = {"render": render_times(base)}
            token = read_token(data / "operator.token")
            robots = SyntheticRobots(endpoint, "default", graph, args.robots)
            time.sleep(2)
            req = urllib.request.Request(
                base + "/api/v1/missions",
                data=json.dumps({"robots": robots.ids, "seed": 1}).encode(),
                headers={"Authorization": f"Bearer {token}", "Content-Type": "application/json"},
            )
            robots.mission = json.loads(urllib.request.urlopen(req).read())["id"]
            out["live"] = [live_view(base, token, robots, args.seconds, animate) for animate in (False, True)]
            return out
        finally:
            if robots is not None:
                robots.close()
            proc.terminate()
            proc.wait(30)


def screenshots(out_dir: Path) -> None:
    """The main views of a real fleet-sim (3 agents on OFFICE): missions flown, a retrain, a replay."""
    from playwright.sync_api import sync_playwright

    out_dir.mkdir(parents=True, exist_ok=True)
    graph = builtin_graph("office")
    with tempfile.TemporaryDirectory(prefix="mures-shots-") as tmp:
        fleet = launch(graph, ["--env", "office"], uniform_walk(graph), Sensor(), 3, Path(tmp), step_delay=0.05)
        try:
            ids = ["r1", "r2", "r3"]
            for k in range(12):
                fleet.fly(ids, seed=k)
            run = fleet.api.post("/api/v1/training-runs", {"episodes": 4096, "gate": False, "seed": 1})
            while fleet.api.get(f"/api/v1/training-runs/{run['id']}")["status"] in ("queued", "running"):
                time.sleep(0.5)
            for k in range(12, 18):
                fleet.fly(ids, seed=k)
            done = fleet.api.get("/api/v1/missions?limit=1")["items"][0]["id"]
            token = read_token(Path(tmp) / "server" / "operator.token")
            with sync_playwright() as p:
                browser = p.chromium.launch(executable_path=chromium())
                page = browser.new_page(viewport={"width": 1400, "height": 860})
                page.goto(fleet.api.base + "/signin")
                page.screenshot(path=str(out_dir / "signin.png"))
                page.get_by_label("Token").fill(token)
                page.get_by_role("button", name="Sign in").click()
                page.wait_for_selector("body[data-ready='1']")
                page.check("#show-truth")
                fleet.api.post("/api/v1/missions", {"seed": 4, "max_steps": 150})
                page.wait_for_selector("svg#map g.robot[data-robot='r3']")
                page.locator("#fleet-table tr[data-robot='r2'] td").first.click()
                time.sleep(1.5)
                page.screenshot(path=str(out_dir / "fleet.png"))
                for path, name in (
                    ("/missions", "missions"),
                    ("/policies", "policies"),
                    ("/training", "training"),
                    ("/data", "data"),
                ):
                    page.goto(fleet.api.base + path)
                    page.wait_for_selector("body[data-ready='1']")
                    time.sleep(1)
                    page.screenshot(path=str(out_dir / f"{name}.png"))
                page.goto(f"{fleet.api.base}/missions/{done}")
                page.wait_for_selector("body[data-ready='1']")
                page.locator("#replay-t").fill(str(min(12, int(page.locator("#replay-last").inner_text()))))
                time.sleep(0.5)
                page.screenshot(path=str(out_dir / "replay.png"))
                browser.close()
        finally:
            fleet.close()
    print(f"screenshots in {out_dir}: {', '.join(sorted(p.name for p in out_dir.glob('*.png')))}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--robots", type=int, default=20)
    ap.add_argument("--seconds", type=float, default=30.0)
    ap.add_argument("--screenshots", metavar="DIR", help="also save the main views of a fleet-sim as PNG here")
    ap.add_argument("--out", metavar="FILE", help="also write the figures as JSON here")
    ap.add_argument("--no-figures", action="store_true", help="only the screenshots")
    args = ap.parse_args()
    if not args.no_figures:
        res = figures(args)
        print(json.dumps(res, indent=1))
        if args.out:
            Path(args.out).write_text(json.dumps(res, indent=1) + "\n")
    if args.screenshots:
        screenshots(Path(args.screenshots))


if __name__ == "__main__":
    main()
