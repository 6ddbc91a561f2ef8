"""The operator console in a real browser: Playwright driving Chromium (Debian's package, through
executable_path: Playwright's own download cannot reach its host here) against a fleet-sim on
loopback (a server process, the simulated world, three robot-agent processes).

One operator's session, in order: a wrong token is refused; sign in; the robots appear and move;
start a mission, watch it finish, replay it and export it; retrain and watch the run to a new
version; roll back; then sign in with the agent token and find every action refused.

Skipped when no Chromium is installed; `.ci/run` installs it and sets MURES_REQUIRE_BROWSER=1, so
in CI a missing browser is a failure, not a skip."""

from __future__ import annotations

import os
import shutil
import time
from pathlib import Path

import pytest

from shared.core.files import read_token
from shared.core.graph import builtin_graph
from shared.core.models import Sensor, uniform_walk
from shared.tools.fleetsim import launch

pytestmark = pytest.mark.slow

CHROMIUM = os.environ.get("MURES_CHROMIUM") or shutil.which("chromium") or shutil.which("chromium-browser")
playwright = pytest.importorskip("playwright.sync_api")
if CHROMIUM is None:
    if os.environ.get("MURES_REQUIRE_BROWSER") == "1":  # set by .ci/run: a missing browser fails CI
        raise RuntimeError("MURES_REQUIRE_BROWSER=1 but no chromium on PATH (apt-get install chromium)")
    pytest.skip("no Chromium on this machine (apt-get install chromium)", allow_module_level=True)

ROBOTS = 3
WAIT_MS = 60_000


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    graph = builtin_graph("office")
    f = launch(
        graph,
        ["--env", "office"],
        uniform_walk(graph),
        Sensor(),
        ROBOTS,
        tmp_path_factory.mktemp("console-fleet"),
        step_delay=0.15,  # a visible pace
        server_extra=["--init-policy", "untrained"],  # the seeded missions below are this version's
    )
    yield f
    f.close()


@pytest.fixture(scope="module")
def browser():
    with playwright.sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM)
        yield b
        b.close()


@pytest.fixture
def page(browser):
    context = browser.new_context(viewport={"width": 1400, "height": 900}, accept_downloads=True)
    pg = context.new_page()
    errors: list[str] = []
    pg.on("pageerror", lambda e: errors.append(str(e)))
    pg.set_default_timeout(WAIT_MS)
    yield pg
    context.close()
    assert errors == [], errors  # no script error on any page


def sign_in(pg, base: str, token: str) -> None:
    pg.goto(f"{base}/signin")
    pg.get_by_label("Token").fill(token)
    pg.get_by_role("button", name="Sign in").click()
    pg.wait_for_selector("body[data-ready='1']")


def goto(pg, url: str) -> None:
    pg.goto(url)
    pg.wait_for_selector("body[data-ready='1']")


def wait_for(pred, what: str, timeout: float = WAIT_MS / 1000):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        got = pred()
        if got:
            return got
        time.sleep(0.1)
    raise AssertionError(f"timed out waiting for {what}")


def test_an_operators_session(fleet, page, tmp_path):
    base = fleet.api.base
    data = fleet.workdir / "server"
    op_token, agent_token = read_token(data / "operator.token"), read_token(data / "agent.token")
    pg = page

    # a wrong token: a clear message, no way in
    pg.goto(f"{base}/")
    pg.wait_for_url("**/signin**")
    pg.get_by_label("Token").fill("not-a-token")
    pg.get_by_role("button", name="Sign in").click()
    pg.wait_for_selector("#signin-error:not([hidden])")  # the server's answer arrives after the click
    assert "not valid for this server" in pg.locator("#signin-error").inner_text()

    # sign in: the fleet appears, every robot online (on the map once it reports a position)
    sign_in(pg, base, op_token)
    assert pg.locator("#role").inner_text() == "operator"
    for r in ("r1", "r2", "r3"):
        pg.wait_for_selector(f"#fleet-table tr[data-robot='{r}']")
    assert "online" in pg.locator("#fleet-table tr[data-robot='r1'] td").nth(1).inner_text()

    # a second tab keeps the live map open (sessionStorage is per tab: sign in there too) and
    # records every node it draws r1 on
    live = pg.context.new_page()
    sign_in(live, base, op_token)
    live.locator("#fleet-table tr[data-robot='r1'] td").first.click()
    live.evaluate(
        """() => { window.seen = new Set();
        new MutationObserver(() => { const g = document.querySelector("svg#map g.robot[data-robot='r1']");
          if (g) window.seen.add(g.dataset.node); }).observe(document.querySelector("svg#map"),
          {subtree: true, childList: true, attributes: true}); }"""
    )

    # start a mission from the missions page (all robots, a step limit)
    goto(pg, f"{base}/missions")
    for r in ("r1", "r2", "r3"):
        pg.wait_for_selector(f"#mission-robots input[value='{r}']")
    pg.fill("#mission-steps", "60")
    pg.fill("#mission-seed", "4")  # a mission of 45 steps (seeded: the same every run)
    pg.select_option("#mission-capture", "auto")
    pg.click("#start-mission")
    pg.wait_for_selector("#notice.ok")
    mission = pg.locator("#missions-table tbody tr").first.get_attribute("data-mission")
    params = fleet.api.get(f"/api/v1/missions/{mission}")["params"]
    assert mission and params["max_steps"] == 60 and params["capture"] == "auto"

    # on the live map the robots appear and move; the selected robot's belief colours the map
    for r in ("r1", "r2", "r3"):
        live.wait_for_selector(f"svg#map g.robot[data-robot='{r}']")
    wait_for(lambda: live.evaluate("() => window.seen.size") >= 3, "robot r1 drawn on three different nodes")
    wait_for(
        lambda: live.evaluate(
            "() => [...document.querySelectorAll('svg#map .node')].some(c => c.getAttribute('fill') !== '#fff')"
        ),
        "r1's belief on the map",
    )
    live.close()

    # watch it finish on the missions page
    goto(pg, f"{base}/missions")
    row = pg.locator(f"#missions-table tr[data-mission='{mission}']")
    wait_for(lambda: row.get_attribute("data-status") in ("completed", "captured"), "the mission to end")
    m = fleet.api.get(f"/api/v1/missions/{mission}")
    outcome = row.locator("td.outcome").inner_text()
    if m["outcome"]["captured"]:
        assert f"t = {m['outcome']['capture_time']}" in outcome, outcome
    else:  # the table says when and after how many steps (a loaded machine can withdraw a slow robot)
        assert outcome.startswith(f"not captured: ended after {m['outcome']['steps']} steps"), outcome

    # replay it: the slider walks the mission; beliefs recomputed; the MCAP export downloads
    row.locator("a").first.click()
    pg.wait_for_selector("body[data-ready='1']")
    last = int(pg.locator("#replay-last").inner_text())
    assert last == max(len(fleet.api.get(f"/api/v1/episodes/{r}/{mission}")["steps"]) for r in m["robots"]) - 1
    pg.locator("#replay-t").fill(str(last))
    assert pg.locator("#replay-step").inner_text() == str(last)
    rec = fleet.api.get(f"/api/v1/episodes/r2/{mission}")
    pg.select_option("#replay-robot", "r2")
    node_at_end = rec["steps"][min(last, len(rec["steps"]) - 1)]["node"]
    assert pg.locator("#replay-table tr[data-robot='r2'] td").nth(1).inner_text() == str(node_at_end)
    with pg.expect_download() as dl:
        pg.click("#export-mcap")
    path = tmp_path / "m.mcap"
    dl.value.save_as(path)
    from mcap.reader import make_reader

    with open(path, "rb") as fh:
        topics = {ch.topic for _s, ch, _m in make_reader(fh).iter_messages()}
    assert {"/map", "/robots/r2/state", "/robots/r2/belief", "/mission/outcome"} <= topics

    # retrain from the console and watch the run to a new version
    goto(pg, f"{base}/training")
    pg.fill("#run-episodes", "512")
    pg.fill("#run-gate-episodes", "50")
    pg.fill("#run-min-missions", "1")  # the fleet has flown a handful of missions
    pg.fill("#run-canary-pairs", "0")  # current at once: no trial
    pg.uncheck("#run-gate")  # publish whatever it learns: this is about the console, not the gate
    pg.click("#start-run")
    pg.wait_for_selector("#notice.ok")
    run = pg.locator("#runs-table tbody tr").first
    wait_for(lambda: run.get_attribute("data-status") in ("succeeded", "failed"), "the training run to end", 300)
    assert run.get_attribute("data-status") == "succeeded", pg.locator("#run-error").inner_text()
    pg.wait_for_selector("svg#curve polyline.curve-line")
    assert "published v2" in pg.locator("#run-message").inner_text()
    assert fleet.api.get("/api/v1/policies/current")["version"] == 2

    # best of two candidates: the run's table shows each beside the current version
    pg.select_option("#run-algorithm", "best")
    assert pg.locator("#run-candidates").is_visible() and not pg.locator("#run-beta").is_visible()
    for box in pg.locator("#run-candidates input").all():
        box.set_checked(box.get_attribute("value") in ("cepg", "mappo"))
    pg.check("#run-gate")  # published only if better than v2: either way the table is there
    pg.click("#start-run")
    pg.wait_for_selector("#notice.ok")
    run = pg.locator("#runs-table tbody tr").first
    wait_for(lambda: run.get_attribute("data-status") in ("succeeded", "failed"), "the best run to end", 300)
    pg.wait_for_selector("#candidates-table tr[data-method='mappo']")
    shown = [r.get_attribute("data-method") for r in pg.locator("#candidates-table tbody tr").all()]
    assert shown == ["current", "cepg", "mappo"]
    best = fleet.api.get("/api/v1/training-runs")["items"][-1]
    assert best["params"]["candidates"] == ["cepg", "mappo"] and best["params"]["episodes"] == 512
    chosen = best["metrics"]["chosen"]
    assert "(chosen)" in pg.locator(f"#candidates-table tr[data-method='{chosen}']").inner_text()
    if best["status"] == "succeeded":  # v3: the rest of the test starts from v2 again
        fleet.api.post("/api/v1/policies/current", {"version": 2})

    # a MASAC run, cancelled from the console
    pg.select_option("#run-algorithm", "masac")
    pg.fill("#run-episodes", "2000000")
    pg.click("#start-run")
    pg.wait_for_selector(
        "#runs-table tbody tr[data-status='running'] button, #runs-table tbody tr[data-status='queued'] button"
    )
    pg.locator("#runs-table tbody tr").first.locator("button").click()
    wait_for(
        lambda: pg.locator("#runs-table tbody tr").first.get_attribute("data-status") == "cancelled", "the cancel", 120
    )

    # roll back to version 1, confirming
    goto(pg, f"{base}/policies")
    assert "512 episodes" in pg.locator("#policies-table tr[data-version='2'] td.trained").inner_text()
    pg.locator("#policies-table tr[data-version='1'] button[data-action='promote']").click()
    assert "Roll back to v1" in pg.locator("#confirm-text").inner_text()
    pg.click("#confirm-ok")
    pg.wait_for_selector("#policies-table tr[data-version='1'] .badge")
    assert fleet.api.get("/api/v1/policies/current")["version"] == 1

    # the agent token: a read-only view, every action refused by the server
    pg.click("#signout")
    sign_in(pg, base, agent_token)
    assert pg.locator("#role").inner_text() == "read-only (agent token)"
    goto(pg, f"{base}/missions")
    pg.wait_for_selector("#mission-robots input[value='r1']")
    before = fleet.api.get("/api/v1/missions")["total"]
    pg.click("#start-mission")
    pg.wait_for_selector("#notice:not([hidden])")
    assert "Refused" in pg.locator("#notice").inner_text() and "operator token" in pg.locator("#notice").inner_text()
    assert fleet.api.get("/api/v1/missions")["total"] == before
    goto(pg, f"{base}/policies")
    pg.locator("#policies-table tr[data-version='2'] button[data-action='promote']").click()
    pg.click("#confirm-ok")
    pg.wait_for_selector("#notice:not([hidden])")
    assert "Refused" in pg.locator("#notice").inner_text()
    assert fleet.api.get("/api/v1/policies/current")["version"] == 1
    goto(pg, f"{base}/training")
    pg.click("#start-run")
    pg.wait_for_selector("#notice:not([hidden])")
    assert "Refused" in pg.locator("#notice").inner_text()
    assert len(fleet.api.get("/api/v1/training-runs")["items"]) == 3


def test_a_robot_that_drops_off_is_flagged_and_alerted(fleet, page):
    base = fleet.api.base
    sign_in(page, base, read_token(fleet.workdir / "server" / "operator.token"))
    page.wait_for_selector("#fleet-table tr[data-robot='r3']")
    fleet.stop_agent("r3")
    try:
        cell = page.locator("#fleet-table tr[data-robot='r3'] td").nth(1)
        wait_for(lambda: cell.inner_text() == "offline (lost)", "r3 to show as lost")
        page.wait_for_selector(".alert[data-kind='robot-lost']")
        assert "robot r3 is offline" in page.locator(".alert[data-kind='robot-lost']").inner_text()
        assert page.locator("svg#map g.robot[data-robot='r3']").count() == 0
    finally:
        fleet.start_agent("r3")


def test_pages_without_a_token_send_the_browser_to_sign_in(fleet, page):
    for path in ("/", "/missions", "/policies", "/training", "/data", "/missions/x"):
        page.goto(f"{fleet.api.base}{path}")
        page.wait_for_url("**/signin?next=**")
        assert Path(page.url.split("next=")[1].split("&")[0].replace("%2F", "/")).as_posix() == path


# What an operator needs at each size: nothing wider than the window, every column of every table
# inside its card, every button on screen (tables wrap their cells instead; console.css).
SIZES = {"laptop": (1366, 768), "phone": (390, 844)}
LAYOUT_JS = """() => {
  const w = window.innerWidth;
  const tables = [...document.querySelectorAll("table.grid")].filter((t) => t.offsetParent !== null);
  return {
    width: w,
    page: document.documentElement.scrollWidth,
    tables: tables.map((t) => [t.id, t.getBoundingClientRect().right, t.parentElement.getBoundingClientRect().right]),
    buttons: [...document.querySelectorAll("main button")].filter((b) => b.offsetParent !== null)
      .map((b) => [b.textContent, b.getBoundingClientRect().right]),
    header: [...document.querySelectorAll("header.top nav a, header.top .who")]
      .map((a) => [a.textContent, a.getBoundingClientRect().right]),
  };
}"""


@pytest.mark.parametrize("size", SIZES)
def test_every_table_and_action_fits_a_laptop_and_a_phone(fleet, browser, size):
    width, height = SIZES[size]
    context = browser.new_context(viewport={"width": width, "height": height})
    pg = context.new_page()
    pg.set_default_timeout(WAIT_MS)
    shots = os.environ.get("MURES_CONSOLE_SCREENSHOTS")  # e.g. docs/console: the pictures docs/ shows
    try:
        sign_in(pg, fleet.api.base, read_token(fleet.workdir / "server" / "operator.token"))
        fleet.fly(["r1", "r2"], seed=11)  # a mission in every list
        for page in ("/", "/missions", "/policies", "/training", "/data"):
            goto(pg, f"{fleet.api.base}{page}")
            pg.wait_for_selector("table.grid tbody tr", state="attached")
            time.sleep(0.5)  # the stream's first fill
            got = pg.evaluate(LAYOUT_JS)
            where = f"{page} at {width} px"
            assert got["page"] <= width, f"{where}: the page is {got['page']} px wide"
            for table, right, card in got["tables"]:
                assert right <= card + 1, f"{where}: table {table} overflows its card ({right} > {card})"
            for text, right in got["buttons"] + got["header"]:
                assert right <= width, f"{where}: {text!r} is off-screen ({right} > {width})"
            if page == "/policies":
                versions = pg.locator("#policies-table tbody tr").count()
                assert pg.locator("#policies-table .badge").count() == 1  # the current one, on screen
                assert pg.locator("#policies-table button[data-action='promote']").count() == versions - 1
            if page == "/" and size == "phone":  # the fleet first, then a map that fits the screen
                table = pg.locator("#fleet-table").bounding_box()
                svg = pg.locator("svg#map").bounding_box()
                assert table["y"] < svg["y"] and svg["height"] <= 0.95 * width + 1 and svg["width"] <= width
                assert pg.locator("#fleet-table th:visible").all_inner_texts() == [
                    "robot",
                    "state",
                    "mission",
                    "step",
                    "node",
                ]
            if shots:
                name = "fleet" if page == "/" else page.strip("/")
                pg.screenshot(path=str(Path(shots) / f"{name}-{width}.png"), full_page=True)
    finally:
        context.close()
