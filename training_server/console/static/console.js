// MuRES fleet console: one script, no framework, no build step.
//
// Every page is rendered by the server without fleet data; this script fills it from the REST API
// (/api/v1, with the token the operator signed in with, kept in sessionStorage for this tab) and
// from the event stream GET /api/v1/events (server-sent events read through fetch(), so that the
// token travels in the Authorization header as on every other call).
"use strict";

const TOKEN_KEY = "mures.token";
const ROLE_KEY = "mures.role";
const TRUTH_KEY = "mures.showTruth";
const ANIMATE_KEY = "mures.animate";
const SVGNS = "http://www.w3.org/2000/svg";
window.muresStats = {}; // events received per kind, for measurements

// ------------------------------------------------------------------ small helpers
const $ = (sel, root = document) => root.querySelector(sel);

function el(tag, attrs = {}, ...children) {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) {
    if (v === null || v === undefined || v === false) continue;
    if (k === "class") e.className = v;
    else if (k.startsWith("on")) e.addEventListener(k.slice(2), v);
    else e.setAttribute(k, v === true ? "" : v);
  }
  for (const c of children) if (c !== null && c !== undefined) e.append(c instanceof Node ? c : String(c));
  return e;
}

function sv(tag, attrs = {}) {
  const e = document.createElementNS(SVGNS, tag);
  for (const [k, v] of Object.entries(attrs)) e.setAttribute(k, v);
  return e;
}

function fmtTime(unix) {
  return unix ? new Date(unix * 1000).toLocaleString() : "—";
}

function fmtAgo(unix) {
  if (!unix) return "—";
  const s = Math.max(0, Date.now() / 1000 - unix);
  if (s < 60) return `${s.toFixed(0)} s ago`;
  if (s < 3600) return `${(s / 60).toFixed(0)} min ago`;
  return `${(s / 3600).toFixed(1)} h ago`;
}

function fmtNum(x, digits = 2) {
  return x === null || x === undefined ? "—" : Number(x).toFixed(digits);
}

function notice(text, ok = false) {
  const n = $("#notice");
  if (!n) return;
  n.textContent = text;
  n.className = ok ? "notice ok" : "notice";
  n.hidden = false;
  clearTimeout(notice.timer);
  notice.timer = setTimeout(() => (n.hidden = true), ok ? 6000 : 15000);
}

// ------------------------------------------------------------------ the API
class ApiError extends Error {
  constructor(status, message) {
    super(message);
    this.status = status;
  }
}

function signOut(reason) {
  sessionStorage.removeItem(TOKEN_KEY);
  sessionStorage.removeItem(ROLE_KEY);
  const next = encodeURIComponent(location.pathname);
  location.assign(`/signin?next=${next}` + (reason ? `&reason=${encodeURIComponent(reason)}` : ""));
}

async function api(path, { method = "GET", body, raw = false, token } = {}) {
  const headers = { Authorization: `Bearer ${token || sessionStorage.getItem(TOKEN_KEY) || ""}` };
  if (body !== undefined) headers["Content-Type"] = "application/json";
  const r = await fetch(path, { method, headers, body: body === undefined ? undefined : JSON.stringify(body) });
  if (!r.ok) {
    let msg = `${r.status} ${r.statusText}`;
    try {
      msg = (await r.json()).error || msg;
    } catch (_e) {
      /* not JSON: keep the status line */
    }
    if (r.status === 401 && !token) signOut("the server no longer accepts this token");
    throw new ApiError(r.status, msg);
  }
  return raw ? r : r.json();
}

// An operator action: the server's answer (or refusal) is shown to the operator.
async function act(what, fn) {
  try {
    const out = await fn();
    notice(what, true);
    return out;
  } catch (e) {
    notice(e.status === 403 ? `Refused: ${e.message} (signed in read-only)` : `${e.message}`);
    return null;
  }
}

// The event stream: calls handlers[event](data); reconnects after a drop. Returns {close()}.
function openStream(params, handlers) {
  let ctrl = null;
  let closed = false;
  async function run() {
    while (!closed) {
      ctrl = new AbortController();
      try {
        const qs = new URLSearchParams(params).toString();
        const r = await fetch(`/api/v1/events${qs ? "?" + qs : ""}`, {
          headers: { Authorization: `Bearer ${sessionStorage.getItem(TOKEN_KEY) || ""}` },
          signal: ctrl.signal,
        });
        if (r.status === 401) return signOut("the server no longer accepts this token");
        if (!r.ok || !r.body) throw new Error(`stream: ${r.status}`);
        const reader = r.body.getReader();
        const dec = new TextDecoder();
        let buf = "";
        for (;;) {
          const { value, done } = await reader.read();
          if (done) break;
          buf += dec.decode(value, { stream: true });
          let cut;
          while ((cut = buf.indexOf("\n\n")) >= 0) {
            const block = buf.slice(0, cut);
            buf = buf.slice(cut + 2);
            let event = "message";
            const data = [];
            for (const line of block.split("\n")) {
              if (line.startsWith("event: ")) event = line.slice(7);
              else if (line.startsWith("data: ")) data.push(line.slice(6));
            }
            if (!data.length) continue;
            window.muresStats[event] = (window.muresStats[event] || 0) + 1; // read by benchmarks/console.py
            if (handlers[event]) handlers[event](JSON.parse(data.join("\n")));
          }
        }
      } catch (e) {
        if (closed) return;
      }
      if (!closed) await new Promise((ok) => setTimeout(ok, 2000));
    }
  }
  run();
  return {
    close() {
      closed = true;
      if (ctrl) ctrl.abort();
    },
  };
}

// The stream's status on a page: its alerts shown, and refresh() called whenever keyOf(status)
// changes after the first (the page loads its own data first). Other handlers as openStream's.
function followStatus(ctx, keyOf, refresh, handlers = {}) {
  let key = null;
  return openStream({}, {
    ...handlers,
    status: (s) => {
      ctx.status(s);
      const k = keyOf(s);
      if (key !== null && k !== key) refresh();
      key = k;
    },
  });
}

// ------------------------------------------------------------------ the map
// heat(v) for v in [0, 1]: white -> amber -> red
function heat(v) {
  const t = Math.max(0, Math.min(1, v));
  const r = 255;
  const g = Math.round(255 - t * (255 - 60));
  const b = Math.round(255 - Math.min(1, t * 1.6) * 255);
  return `rgb(${r},${g},${b})`;
}

class MapView {
  // svg: the <svg>; map: GET /api/v1/map; layout: GET /api/v1/map/layout
  constructor(svg, map, layout) {
    this.svg = svg;
    this.map = map;
    this.labels = map.nodes;
    this.pos = {};
    for (const lab of map.nodes) this.pos[lab] = layout.positions[String(lab)];
    const xs = map.nodes.map((l) => this.pos[l][0]);
    const ys = map.nodes.map((l) => this.pos[l][1]);
    const pad = 0.05;
    let [x0, x1, y0, y1] = [Math.min(...xs), Math.max(...xs), Math.min(...ys), Math.max(...ys)];
    const img = layout.image; // the building's map under the graph (training-server --map-image)
    if (img) [x0, x1, y0, y1] = [Math.min(x0, img.x), Math.max(x1, img.x + img.width), Math.min(y0, img.y), Math.max(y1, img.y + img.height)];
    svg.setAttribute("viewBox", `${x0 - pad} ${y0 - pad} ${x1 - x0 + 2 * pad} ${y1 - y0 + 2 * pad}`);
    svg.setAttribute("preserveAspectRatio", "xMidYMid meet");
    this.r = Math.min(0.018, 0.3 / Math.sqrt(map.nodes.length)); // layout.py's node_radius
    svg.replaceChildren();
    this.gMap = svg.appendChild(sv("g", { class: "building" }));
    if (img) this.drawBuilding(img);
    this.gEdges = svg.appendChild(sv("g"));
    this.gFlows = svg.appendChild(sv("g"));
    this.gNodes = svg.appendChild(sv("g"));
    this.gMarks = svg.appendChild(sv("g"));
    this.gRobots = svg.appendChild(sv("g"));
    for (const [u, v] of map.edges) {
      const [a, b] = [this.pos[u], this.pos[v]];
      this.gEdges.append(sv("line", { class: "edge", x1: a[0], y1: a[1], x2: b[0], y2: b[1] }));
    }
    this.nodeEls = {};
    for (const lab of map.nodes) {
      const [x, y] = this.pos[lab];
      const c = sv("circle", { class: "node" + (lab === map.start_node ? " start" : ""), cx: x, cy: y, r: this.r, fill: "#fff" });
      const title = sv("title");
      title.textContent = `node ${lab}`;
      c.append(title);
      this.gNodes.append(c);
      if (map.nodes.length <= 150) {
        const t = sv("text", { class: "node-label", x, y: y + this.r * 0.35, "font-size": this.r * 0.9 });
        t.textContent = lab;
        this.gNodes.append(t);
      }
      this.nodeEls[lab] = c;
    }
    this.robotEls = {};
    this.targetEls = {};
    this.onRobotClick = null;
  }

  // the building's map image, fetched with the token (an <image href> would go without it)
  async drawBuilding(img) {
    try {
      const blob = await (await api(img.url, { raw: true })).blob();
      const im = sv("image", { x: img.x, y: img.y, width: img.width, height: img.height, preserveAspectRatio: "none", class: "building-map" });
      im.setAttribute("href", URL.createObjectURL(blob));
      this.gMap.replaceChildren(im);
    } catch (_e) {
      /* no picture: the graph alone, as for a graph without a map */
    }
  }

  // values: n numbers in the map's node order (null: plain), from their minimum (white) to their
  // maximum (red): a uniform belief, which says nothing, stays white
  setHeat(values, titleOf) {
    const lo = values ? Math.min(...values) : 0;
    const span = values ? Math.max(...values) - lo : 0;
    this.labels.forEach((lab, i) => {
      const c = this.nodeEls[lab];
      c.setAttribute("fill", values && span > 1e-12 ? heat((values[i] - lo) / span) : "#fff");
      c.firstChild.textContent = values ? `node ${lab}: ${titleOf ? titleOf(values[i]) : values[i].toFixed(4)}` : `node ${lab}`;
    });
  }

  // robots: [{id, node, detect, falseAlarm, selected}]; drawn beside their node (up and to the
  // right, so that its label stays readable), robots on one node spread around it
  setRobots(robots) {
    const byNode = {};
    for (const r of robots) (byNode[r.node] = byNode[r.node] || []).push(r);
    const keep = new Set();
    for (const group of Object.values(byNode)) {
      group.forEach((r, k) => {
        const [x, y] = this.pos[r.node];
        const a = -Math.PI / 4 + (2 * Math.PI * k) / group.length;
        const off = this.r * 1.45;
        let g = this.robotEls[r.id];
        if (!g) {
          g = sv("g", { class: "robot", "data-robot": r.id });
          g.append(sv("circle", { class: "ring", r: this.r * 1.0 }), sv("circle", { r: this.r * 0.72 }));
          const t = sv("text", { "font-size": this.r * 0.7 });
          t.textContent = r.id.length > 3 ? r.id.slice(-3) : r.id;
          g.append(t);
          const title = sv("title");
          g.append(title);
          g.addEventListener("click", () => this.onRobotClick && this.onRobotClick(r.id));
          this.gRobots.append(g);
          this.robotEls[r.id] = g;
        }
        g.lastChild.textContent = `robot ${r.id} at node ${r.node}` + (r.detect ? (r.falseAlarm ? " (false alarm)" : " (detection)") : "");
        g.style.transform = `translate(${x + off * Math.cos(a)}px, ${y + off * Math.sin(a)}px)`;
        g.classList.toggle("detect", !!r.detect && !r.falseAlarm);
        g.classList.toggle("false-alarm", !!r.detect && !!r.falseAlarm);
        g.classList.toggle("selected", !!r.selected);
        g.dataset.node = r.node;
        keep.add(r.id);
      });
    }
    for (const [id, g] of Object.entries(this.robotEls)) {
      if (!keep.has(id)) {
        g.remove();
        delete this.robotEls[id];
      }
    }
  }

  // targets: {mission_id: node label}
  setTargets(targets) {
    for (const [mid, node] of Object.entries(targets)) {
      let e = this.targetEls[mid];
      if (!e) {
        const s = this.r * 0.9;
        e = sv("rect", { class: "target", x: -s / 2, y: -s / 2, width: s, height: s, "data-mission": mid });
        e.append(sv("title"));
        this.gMarks.append(e);
        this.targetEls[mid] = e;
      }
      const [x, y] = this.pos[node];
      e.style.transform = `translate(${x}px, ${y}px) rotate(45deg)`;
      e.firstChild.textContent = `true target of ${mid} at node ${node}`;
      e.dataset.node = node;
    }
    for (const [mid, e] of Object.entries(this.targetEls)) {
      if (!(mid in targets)) {
        e.remove();
        delete this.targetEls[mid];
      }
    }
  }

  // flows: [[u, v, weight in [0, 1]]] drawn as edge widths
  setFlows(flows) {
    this.gFlows.replaceChildren();
    for (const [u, v, w] of flows) {
      const [a, b] = [this.pos[u], this.pos[v]];
      this.gFlows.append(sv("line", { class: "flow", x1: a[0], y1: a[1], x2: b[0], y2: b[1], "stroke-width": this.r * 1.6 * w }));
    }
  }

  // rings: n values drawn as ring widths around the nodes, from their minimum (none) to their maximum
  setRings(values) {
    this.gMarks.replaceChildren();
    const lo = Math.min(...values);
    const span = Math.max(...values) - lo;
    if (span <= 1e-12) return; // uniform: nothing stands out
    this.labels.forEach((lab, i) => {
      if (values[i] <= lo) return;
      const [x, y] = this.pos[lab];
      this.gMarks.append(sv("circle", { class: "b0", cx: x, cy: y, r: this.r * 1.35, "stroke-width": (this.r * 0.6 * (values[i] - lo)) / span }));
    });
  }
}

async function loadMap(svg) {
  const [map, layout] = await Promise.all([api("/api/v1/map"), api("/api/v1/map/layout")]);
  return new MapView(svg, map, layout);
}

// ------------------------------------------------------------------ alerts (every page)
// A detection awaiting an operator carries its two decisions (POST /api/v1/detections/{id}/...).
function detectionButtons(a) {
  const decide = (verb, done) =>
    el(
      "button",
      {
        type: "button",
        "data-action": verb,
        onclick: () => act(done, () => api(`/api/v1/detections/${a.subject}/${verb}`, { method: "POST" })),
      },
      verb === "confirm" ? "Confirm: captured" : "Dismiss: false alarm",
    );
  return el("span", { class: "alert-actions" }, decide("confirm", "Mission ended as captured"), decide("dismiss", "Recorded as a false alarm; the search goes on"));
}

function showAlerts(alerts) {
  const box = $("#alerts");
  box.replaceChildren(
    ...alerts.map((a) =>
      el("div", { class: `alert ${a.level}`, "data-kind": a.kind, "data-subject": a.subject }, a.text, a.kind === "detection" ? detectionButtons(a) : null),
    ),
  );
}

// ------------------------------------------------------------------ pages
const pages = {};

pages.signin = function () {
  const params = new URLSearchParams(location.search);
  const err = $("#signin-error");
  if (params.get("reason")) {
    err.textContent = `Signed out: ${params.get("reason")}.`;
    err.hidden = false;
  }
  $("#signin-form").addEventListener("submit", async (ev) => {
    ev.preventDefault();
    const token = $("#token").value.trim();
    err.hidden = true;
    try {
      const me = await api("/api/v1/whoami", { token });
      sessionStorage.setItem(TOKEN_KEY, token);
      sessionStorage.setItem(ROLE_KEY, me.role);
      const next = params.get("next");
      location.assign(next && next.startsWith("/") && !next.startsWith("//") ? next : "/");
    } catch (e) {
      err.textContent =
        e.status === 401
          ? "This token is not valid for this server. Use the operator token or the agent token from its data directory."
          : e.status === 429
            ? `Too many wrong tokens from this address: ${e.message}`
            : `Cannot sign in: ${e.message}`;
      err.hidden = false;
    }
  });
};

pages.fleet = async function (ctx) {
  const view = await loadMap($("#map"));
  let selected = null;
  let fleet = null;
  let stream = null;
  const animate = $("#animate");
  animate.checked = sessionStorage.getItem(ANIMATE_KEY) === "1";
  $("#map").classList.toggle("animate", animate.checked);
  animate.addEventListener("change", () => {
    sessionStorage.setItem(ANIMATE_KEY, animate.checked ? "1" : "0");
    $("#map").classList.toggle("animate", animate.checked);
  });
  const truthBox = $("#show-truth");
  truthBox.checked = sessionStorage.getItem(TRUTH_KEY) === "1";
  truthBox.addEventListener("change", () => {
    sessionStorage.setItem(TRUTH_KEY, truthBox.checked ? "1" : "0");
    if (fleet) draw();
  });

  const teamBox = $("#team-belief");
  let lastBelief = null; // the selected robot's last beliefs {belief, team_belief}
  function heat() {
    const b = lastBelief;
    const team = teamBox.checked;
    const shown = b && (team ? b.team_belief : b.belief);
    view.setHeat(shown || null);
    if (selected) {
      const what = team ? "the team's belief held by" : "own belief of";
      const missing = b && team && !b.team_belief ? " (it flies alone: no team's belief)" : "";
      $("#belief-of").textContent = `${what} ${selected} (node colour)${missing}`;
    }
  }
  teamBox.addEventListener("change", heat);

  function select(robot) {
    selected = robot === selected ? null : robot;
    lastBelief = null;
    $("#belief-of").textContent = selected ? `belief of ${selected} (node colour)` : "click a robot to see its belief";
    heat();
    connect();
    if (fleet) draw();
  }
  view.onRobotClick = select;

  const rowOf = {}; // robot -> its <tr>, updated in place (a 5 Hz redraw must not rebuild the table)
  function row(a) {
    let tr = rowOf[a.robot_id];
    if (!tr) {
      tr = el("tr", { class: "clickable", "data-robot": a.robot_id });
      // last seen, policy and backend: columns a phone hides (console.css)
      tr.append(...Array.from({ length: 8 }, (_, i) => el("td", { class: [2, 6].includes(i) ? "opt" : i === 7 ? "opt wide" : null })));
      tr.addEventListener("click", (ev) => ev.target.tagName !== "A" && select(a.robot_id));
      rowOf[a.robot_id] = tr;
    }
    const cells = tr.children;
    const set = (i, text, cls) => {
      if (cells[i].textContent !== String(text)) cells[i].textContent = text;
      if (cls !== undefined && cells[i].className !== cls) cells[i].className = cls;
    };
    set(0, a.robot_id);
    const mode = a.mode ? ` · ${a.mode === "own" ? "on its own" : a.mode === "partial" ? "team (partial)" : "team"}` : "";
    const failed = a.last_failure ? ` · last mission failed: ${a.last_failure.reason}` : "";
    const state =
      a.state === "revoked"
        ? "revoked: its credentials were taken away"
        : a.online
          ? `online · ${a.state}${mode}${failed}`
          : a.down_reason
            ? `down: ${a.down_reason}`
            : "offline (lost)";
    set(1, state, `state-${a.state === "revoked" ? "revoked" : a.online ? "online" : "offline"}`);
    cells[2].dataset.ts = a.last_seen;
    set(2, fmtAgo(a.last_seen));
    if ((cells[3].dataset.mission || "") !== (a.mission_id || "")) {
      cells[3].dataset.mission = a.mission_id || "";
      // a long id is shown shortened on one line; the link's title holds it whole
      const link = a.mission_id ? el("a", { href: `/missions/${encodeURIComponent(a.mission_id)}`, class: "mission-id", title: a.mission_id }, a.mission_id) : "—";
      cells[3].replaceChildren(link);
    }
    set(4, a.step ?? "—");
    set(5, a.node ?? "—");
    set(6, a.policy_version ?? "—");
    set(7, a.backend ?? "—");
    tr.classList.toggle("selected", a.robot_id === selected);
    return tr;
  }

  function draw() {
    const robots = [];
    const truth = fleet.truth || {};
    for (const a of fleet.agents) {
      const t = a.mission_id ? truth[a.mission_id] : null;
      const tr = t && t.robots ? t.robots[a.robot_id] : null;
      const detect = a.z === 1;
      const falseAlarm = detect && truthBox.checked && tr && t.t === a.step ? !tr.seen : false;
      if (a.node !== null && a.online) robots.push({ id: a.robot_id, node: a.node, detect, falseAlarm, selected: a.robot_id === selected });
    }
    const rows = fleet.agents.map(row);
    const body = $("#fleet-table tbody");
    if (rows.length !== body.children.length || rows.some((r, i) => body.children[i] !== r)) body.replaceChildren(...rows);
    $("#fleet-empty").hidden = rows.length > 0;
    $("#online-count").textContent = `${fleet.online} of ${fleet.agents.length} online`;
    view.setRobots(robots);
    const targets = {};
    if (truthBox.checked) for (const [mid, t] of Object.entries(truth)) targets[mid] = t.target;
    view.setTargets(targets);
  }

  function connect() {
    if (stream) stream.close();
    const params = selected ? { belief: selected } : {};
    stream = openStream(params, {
      fleet: (f) => {
        fleet = f;
        draw();
      },
      belief: (b) => {
        if (b.robot_id !== selected) return;
        lastBelief = b;
        heat();
      },
      status: (s) => ctx.status(s),
    });
  }
  connect();
  setInterval(() => {
    for (const td of document.querySelectorAll("td[data-ts]")) td.textContent = fmtAgo(Number(td.dataset.ts));
  }, 1000);
};

pages.missions = async function (ctx) {
  let offset = 0;
  const limit = 20;
  let onlineKey = "";
  const chosen = {};
  async function refresh() {
    const page = await api(`/api/v1/missions?limit=${limit}&offset=${offset}`);
    $("#missions-total").textContent = `(${page.total} in all; ${offset + 1}–${Math.min(offset + limit, page.total)})`;
    $("#missions-newer").disabled = offset === 0;
    $("#missions-older").disabled = offset + limit >= page.total;
    $("#missions-table tbody").replaceChildren(
      ...page.items.map((m) => {
        const o = m.outcome;
        const outcome = !o
          ? "—"
          : o.captured
            ? `captured at t = ${o.capture_time}` + (o.capture_time_s != null ? ` (${o.capture_time_s.toFixed(1)} s)` : "") + (o.captured_by ? ` by ${o.captured_by}` : "")
            : `not captured: ended after ${o.steps} steps${m.ended ? `, ${fmtTime(m.ended)}` : ""}${m.event && m.event.reason ? ` (${m.event.reason})` : ""}`;
        return el(
          "tr",
          { "data-mission": m.id, "data-status": m.status },
          el("td", {}, el("a", { href: `/missions/${encodeURIComponent(m.id)}` }, m.id)),
          el("td", { class: `status-${m.status}` }, m.status),
          el("td", {}, m.robots.join(", ")),
          el("td", {}, m.policy_version ?? "—"),
          el("td", {}, fmtTime(m.created)),
          el("td", { class: "outcome" }, outcome),
          el(
            "td",
            {},
            m.status === "running"
              ? el("button", { type: "button", class: "danger", onclick: () => stop(m.id) }, "Stop")
              : el("a", { href: `/missions/${encodeURIComponent(m.id)}` }, "replay"),
          ),
        );
      }),
    );
  }
  async function stop(id) {
    await act(`Mission ${id} stopped`, () => api(`/api/v1/missions/${encodeURIComponent(id)}/stop`, { method: "POST" }));
    refresh();
  }
  function robots(fleet) {
    const online = fleet.agents.filter((a) => a.online).map((a) => a);
    const key = online.map((a) => `${a.robot_id}:${a.state}`).join(",");
    if (key === onlineKey) return;
    onlineKey = key;
    const box = $("#mission-robots");
    const items = online.map((a) => {
      if (!(a.robot_id in chosen)) chosen[a.robot_id] = true;
      const cb = el("input", { type: "checkbox", value: a.robot_id, checked: chosen[a.robot_id], onchange: (e) => (chosen[a.robot_id] = e.target.checked) });
      return el("label", {}, cb, `${a.robot_id}${a.state === "flying" ? " (flying)" : ""}`);
    });
    box.replaceChildren(el("legend", {}, "Robots"), ...(items.length ? items : [el("span", { class: "muted" }, "no robot online")]));
  }
  $("#mission-form").addEventListener("submit", async (ev) => {
    ev.preventDefault();
    const picked = [...document.querySelectorAll("#mission-robots input:checked")].map((c) => c.value);
    if (!picked.length) return notice("Choose at least one robot online.");
    const body = { robots: picked };
    if ($("#mission-seed").value !== "") body.seed = Number($("#mission-seed").value);
    if ($("#mission-steps").value !== "") body.max_steps = Number($("#mission-steps").value);
    if ($("#mission-seconds").value !== "") body.max_seconds = Number($("#mission-seconds").value);
    if ($("#mission-capture").value !== "") body.capture = $("#mission-capture").value;
    const m = await act("Mission started", () => api("/api/v1/missions", { method: "POST", body }));
    if (m) notice(`Mission ${m.id} started with ${m.robots.join(", ")}`, true);
    offset = 0;
    refresh();
  });
  $("#missions-newer").addEventListener("click", () => ((offset = Math.max(0, offset - limit)), refresh()));
  $("#missions-older").addEventListener("click", () => ((offset += limit), refresh()));
  followStatus(ctx, (s) => s.running_missions.join(",") + "|" + s.episodes.stored, refresh, { fleet: robots });
  await refresh();
};

pages.replay = async function (ctx) {
  const id = document.body.dataset.missionId;
  const view = await loadMap($("#map"));
  let data = null;
  let t = 0;
  let timer = null;
  const slider = $("#replay-t");
  const pick = $("#replay-robot");
  const teamBox = $("#replay-team");

  function at(steps, t) {
    // the robot's step t, or its last one when its record is shorter (it stopped earlier)
    return steps[Math.min(t, steps.length - 1)];
  }
  function draw() {
    const robots = [];
    const rows = [];
    for (const [rid, r] of Object.entries(data.robots)) {
      const k = Math.min(t, r.steps.length - 1);
      const st = at(r.steps, t);
      robots.push({ id: rid, node: st.node, detect: st.z === 1, selected: rid === pick.value });
      let bmax = "—";
      if (r.belief) {
        const b = r.belief[k];
        const i = b.indexOf(Math.max(...b));
        bmax = `${data.nodes[i]} (${b[i].toFixed(3)})`;
      }
      rows.push(el("tr", { "data-robot": rid }, el("td", {}, rid), el("td", {}, st.node), el("td", {}, st.z), el("td", {}, bmax)));
    }
    view.setRobots(robots);
    const sel = data.robots[pick.value];
    if (teamBox.checked && data.team_belief) view.setHeat(data.team_belief[Math.min(t, data.team_belief.length - 1)]);
    else view.setHeat(sel && sel.belief ? sel.belief[Math.min(t, sel.steps.length - 1)] : null);
    $("#replay-table tbody").replaceChildren(...rows);
    $("#replay-step").textContent = t;
    slider.value = t;
  }
  async function load() {
    data = await api(`/api/v1/missions/${encodeURIComponent(id)}/replay`);
    const m = data.mission;
    const o = m.outcome;
    const last = Math.max(0, ...Object.values(data.robots).map((r) => r.steps.length - 1));
    slider.max = last;
    $("#replay-last").textContent = last;
    const facts = [
      ["status", m.status],
      ["robots", m.robots.join(", ")],
      ["records", `${m.episodes_received.length} of ${m.robots.length}`],
      ["policy version", m.policy_version ?? "—"],
      ["started", fmtTime(m.created)],
      [
        "outcome",
        !o
          ? "no record yet"
          : o.captured
            ? `captured at t = ${o.capture_time}${o.capture_time_s != null ? ` (${o.capture_time_s.toFixed(1)} s)` : ""}${o.captured_by ? " by " + o.captured_by : ""}`
            : `not captured: ended after ${o.steps} steps${m.event && m.event.reason ? ` (${m.event.reason})` : ""}`,
      ],
      ["seed", m.params.seed],
    ];
    $("#replay-summary").replaceChildren(...facts.flatMap(([k, v]) => [el("dt", {}, k), el("dd", { "data-fact": k }, v)]));
    const prev = pick.value;
    pick.replaceChildren(
      ...Object.entries(data.robots).map(([rid, r]) => el("option", { value: rid, disabled: !r.belief }, rid + (r.belief ? "" : " (no belief: version gone)"))),
    );
    if (prev && prev in data.robots) pick.value = prev;
    teamBox.disabled = !data.team_belief;
    draw();
  }
  slider.addEventListener("input", () => {
    t = Number(slider.value);
    draw();
  });
  pick.addEventListener("change", draw);
  teamBox.addEventListener("change", draw);
  view.onRobotClick = (rid) => {
    pick.value = rid;
    draw();
  };
  $("#replay-play").addEventListener("click", () => {
    if (timer) {
      clearInterval(timer);
      timer = null;
      $("#replay-play").textContent = "Play";
      return;
    }
    if (t >= Number(slider.max)) t = 0;
    $("#replay-play").textContent = "Pause";
    timer = setInterval(() => {
      if (t >= Number(slider.max)) {
        clearInterval(timer);
        timer = null;
        $("#replay-play").textContent = "Play";
        return;
      }
      t += 1;
      draw();
    }, 250);
  });
  $("#export-mcap").addEventListener("click", async () => {
    try {
      const r = await api(`/api/v1/missions/${encodeURIComponent(id)}/export.mcap`, { raw: true });
      const url = URL.createObjectURL(await r.blob());
      const a = el("a", { href: url, download: `${id}.mcap` });
      document.body.append(a);
      a.click();
      a.remove();
      setTimeout(() => URL.revokeObjectURL(url), 10000);
    } catch (e) {
      notice(`Export failed: ${e.message}`);
    }
  });
  followStatus(ctx, (s) => s.episodes.stored + "|" + s.running_missions.includes(id), load);
  try {
    await load();
  } catch (e) {
    notice(e.status === 404 ? `No mission ${id} on this server.` : e.message);
  }
};

pages.policies = async function (ctx) {
  const dialog = $("#confirm");
  function confirmAction(text) {
    return new Promise((ok) => {
      $("#confirm-text").textContent = text;
      dialog.returnValue = "";
      dialog.addEventListener("close", () => ok(dialog.returnValue === "ok"), { once: true });
      dialog.showModal();
    });
  }
  async function refresh() {
    const [list, runs, perf] = await Promise.all([
      api("/api/v1/policies"),
      api("/api/v1/training-runs"),
      api("/api/v1/policies/performance"),
    ]);
    const runOf = Object.fromEntries(runs.items.map((r) => [r.id, r]));
    const perfOf = Object.fromEntries(perf.items.map((p) => [p.version, p]));
    const rows = [...list.items].reverse().map((p) => {
      const run = p.run_id ? runOf[p.run_id] : null;
      const g = run && run.metrics ? run.metrics.gate : null;
      const gate = g
        ? [
            `${g.passed ? "passed" : "failed"}: ${fmtNum(g.new.mean_capture_time)} vs ${fmtNum(g.current.mean_capture_time)} ${g.unit || "steps"}`,
            el("span", { class: "sub" }, `${g.new.episodes} episodes${g.model ? `, ${g.model}` : ""}`),
          ]
        : [p.run_id ? "—" : "initial"];
      const mt = run && run.metrics ? run.metrics : null;
      const em = mt ? mt.em : null;
      const trained = mt
        ? [
            `${mt.train.episodes.toLocaleString()} episodes in ${fmtNum(mt.train.wall_seconds, 0)} s`,
            el("span", { class: "sub" }, `EM on ${em.missions} missions${em.held_out ? ` (${em.held_out} held out)` : ""} · from v${p.parent} · ${p.run_id}`),
          ]
        : [p.parent ? `from v${p.parent}` : "—"];
      const pf = perfOf[p.version];
      const onClock = pf && pf.mean_capture_time_s !== null && pf.mean_capture_time_s !== undefined
        ? `; ${fmtNum(pf.mean_capture_time_s)} s ± ${pf.ci95_s === null ? "?" : fmtNum(pf.ci95_s)} over ${pf.missions_on_clock} on the clock`
        : "";
      const ct = pf ? `${fmtNum(pf.mean_capture_time)} steps ± ${pf.ci95 === null ? "?" : fmtNum(pf.ci95)} (${pf.missions} missions${onClock})` : "no missions yet";
      const m = p.meta || {};
      const c = m.canary;
      const trial = !c
        ? ["—"]
        : c.state === "flying"
          ? [`on trial beside v${c.baseline}: ${c.pairs} pairs of missions`]
          : c.canary_mean !== undefined
            ? [
                `${c.state}: ${fmtNum(c.canary_mean)} vs ${fmtNum(c.baseline_mean)} ${c.unit || 'steps'} (v${c.baseline})`,
                el("span", { class: "sub" }, `difference ${c.mean_difference >= 0 ? "+" : ""}${fmtNum(c.mean_difference)} ± ${fmtNum(c.ci95)} over ${c.pairs} pairs`),
              ]
            : [c.state];
      const method = [m.algorithm || "cepg", m.variant, m.beta !== undefined ? `beta ${JSON.stringify(m.beta)}` : null].filter(Boolean).join(" · ");
      let action = el("span", { class: "badge operator" }, "current");
      if (!p.current) {
        const verb = p.version < list.current ? `Roll back to v${p.version}` : `Make v${p.version} current`;
        action = el(
          "button",
          {
            type: "button",
            "data-action": "promote",
            onclick: async () => {
              if (!(await confirmAction(`${verb}? Agents take version ${p.version} before their next mission.`))) return;
              await act(`Version ${p.version} is now current`, () => api("/api/v1/policies/current", { method: "POST", body: { version: p.version } }));
              refresh();
            },
          },
          verb,
        );
      }
      // the version, when it was made, and what an operator can do with it, in the first column:
      // always on screen, however narrow the window
      return el(
        "tr",
        { "data-version": p.version, class: p.current ? "selected" : "" },
        el("td", { class: "version" }, el("strong", {}, `v${p.version} `), action, el("span", { class: "sub" }, fmtTime(p.created))),
        el("td", {}, method),
        el("td", { class: "trained" }, ...trained),
        el("td", { class: "gate" }, ...gate),
        el("td", { class: "trial" }, ...trial),
        el("td", { class: "perf" }, ct),
      );
    });
    $("#policies-table tbody").replaceChildren(...rows);
  }
  followStatus(ctx, (s) => `${s.current_policy}|${s.episodes.stored}|${s.runs.map((r) => r.status).join(",")}`, refresh);
  await refresh();
};

pages.training = async function (ctx) {
  let selected = null;
  let runs = [];
  function drawCurve(curve) {
    const svg = $("#curve");
    svg.replaceChildren();
    const W = svg.clientWidth || 500;
    const H = svg.clientHeight || 220;
    svg.setAttribute("viewBox", `0 0 ${W} ${H}`);
    if (!curve || curve.length < 2) {
      const t = sv("text", { x: 12, y: 24, class: "axis-label" });
      t.textContent = "no points yet";
      svg.append(t);
      return;
    }
    const [l, r, top, bot] = [48, W - 10, 10, H - 28];
    const xs = curve.map((p) => p[0]);
    const ys = curve.map((p) => p[1]);
    const [x0, x1] = [Math.min(...xs), Math.max(...xs)];
    const [y0, y1] = [Math.min(...ys), Math.max(...ys)];
    const X = (x) => l + ((x - x0) / (x1 - x0 || 1)) * (r - l);
    const Y = (y) => bot - ((y - y0) / (y1 - y0 || 1)) * (bot - top);
    svg.append(sv("line", { class: "axis", x1: l, y1: bot, x2: r, y2: bot }), sv("line", { class: "axis", x1: l, y1: top, x2: l, y2: bot }));
    svg.append(sv("polyline", { class: "curve-line", points: curve.map((p) => `${X(p[0])},${Y(p[1])}`).join(" ") }));
    const labels = [
      [l, bot + 16, x0.toLocaleString()],
      [r - 60, bot + 16, `${x1.toLocaleString()} episodes`],
      [4, bot, y0.toFixed(1)],
      [4, top + 10, y1.toFixed(1)],
    ];
    for (const [x, y, text] of labels) {
      const t = sv("text", { x, y, class: "axis-label" });
      t.textContent = text;
      svg.append(t);
    }
  }
  function detail() {
    const r = runs.find((x) => x.id === selected);
    if (!r) return;
    $("#run-id").textContent = r.id;
    const p = r.progress || {};
    const bar = $("#run-progress");
    if (r.status === "succeeded") bar.value = bar.max = 1;
    else if (p.phase === "train" && p.total) [bar.max, bar.value] = [p.total, p.episodes];
    else if (p.phase === "em" && p.max_iter) [bar.max, bar.value] = [p.max_iter, p.iteration || 0];
    else bar.removeAttribute("value");
    const team = p.phase === "train" && p.method ? `${p.method} for ${p.robots} robots: ` : "";
    const eta = p.eta_s !== undefined ? `, about ${p.eta_s >= 120 ? Math.round(p.eta_s / 60) + " min" : p.eta_s + " s"} left` : "";
    const where = p.phase === "train" && p.total ? `${team}${p.episodes.toLocaleString()} of ${p.total.toLocaleString()} episodes${eta}` : "";
    $("#run-message").textContent = `${r.status}${p.phase ? " · " + p.phase : ""}${where ? " · " + where : ""}${p.message ? " · " + p.message : ""}${r.version ? ` · published v${r.version}` : ""}`;
    const err = $("#run-error");
    err.hidden = !r.error;
    err.textContent = r.error ? `Why: ${r.error}` : "";
    drawCurve(p.curve);
    candidates(r.metrics || {});
  }
  function candidates(m) {
    const table = $("#candidates-table");
    const rows = m.candidates || [];
    table.hidden = !rows.length;
    table.querySelector("tbody").replaceChildren(
      ...rows.map((c) => {
        const t = c.training;
        const ci = c.ci95 ? `${c.ci95[0].toFixed(2)} – ${c.ci95[1].toFixed(2)}` : "—";
        const diff = c.paired_difference === undefined ? "—" : `${c.paired_difference >= 0 ? "+" : ""}${c.paired_difference.toFixed(2)} ± ${c.paired_ci95.toFixed(2)}`;
        const cost = t ? `${(t.episodes || 0).toLocaleString()} episodes, ${Math.round(t.wall_seconds || 0)} s` : "—";
        const name = c.method === "current" ? "current version" : c.method + (c.method === m.chosen ? " (chosen)" : "");
        return el("tr", { "data-method": c.method }, el("td", {}, name), el("td", {}, c.mean_capture_time.toFixed(2)), el("td", {}, ci), el("td", {}, diff), el("td", {}, cost));
      }),
    );
  }
  function syncForm() {
    const algorithm = $("#run-algorithm").value;
    $("#run-candidates").hidden = algorithm !== "best";
    $("#run-beta").closest("label").hidden = algorithm !== "cepg";
  }
  $("#run-algorithm").addEventListener("change", syncForm);
  syncForm();
  async function refresh() {
    runs = (await api("/api/v1/training-runs")).items.reverse(); // newest first
    if (!selected && runs.length) selected = runs[0].id;
    $("#runs-table tbody").replaceChildren(
      ...runs.map((r) => {
        const p = r.progress || {};
        const prog = p.phase === "train" && p.total ? `${Math.round((100 * p.episodes) / p.total)} %` : p.phase || "—";
        return el(
          "tr",
          { class: "clickable" + (r.id === selected ? " selected" : ""), "data-run": r.id, "data-status": r.status, onclick: () => ((selected = r.id), refresh()) },
          el("td", {}, r.id),
          el("td", { class: `status-${r.status}` }, r.status),
          el("td", {}, fmtTime(r.started)),
          el("td", {}, prog),
          el("td", {}, r.version ? `v${r.version}` : "—"),
          el(
            "td",
            {},
            ["queued", "running"].includes(r.status) && !r.cancel_requested
              ? el(
                  "button",
                  {
                    type: "button",
                    class: "danger",
                    onclick: async (e) => {
                      e.stopPropagation();
                      await act(`Cancelling ${r.id}`, () => api(`/api/v1/training-runs/${encodeURIComponent(r.id)}/cancel`, { method: "POST" }));
                      refresh();
                    },
                  },
                  "Cancel",
                )
              : "",
          ),
        );
      }),
    );
    detail();
  }
  $("#run-form").addEventListener("submit", async (ev) => {
    ev.preventDefault();
    const algorithm = $("#run-algorithm").value;
    const body = {
      algorithm,
      budget_fraction: Number($("#run-budget").value),
      seed: Number($("#run-seed").value),
      gate_episodes: Number($("#run-gate-episodes").value),
      min_missions: Number($("#run-min-missions").value),
      canary_pairs: Number($("#run-canary-pairs").value),
      gate: $("#run-gate").checked,
      promote: $("#run-promote").checked,
    };
    if ($("#run-episodes").value) body.episodes = Number($("#run-episodes").value);
    if (algorithm === "cepg" && $("#run-beta").value) body.beta = Number($("#run-beta").value);
    if (algorithm === "best") body.candidates = [...document.querySelectorAll("#run-candidates input:checked")].map((x) => x.value);
    const sizes = $("#run-team-sizes").value.split(/[\s,]+/).filter(Boolean);
    if (sizes.length) body.team_sizes = sizes.map(Number);
    const r = await act("Training run queued", () => api("/api/v1/training-runs", { method: "POST", body }));
    if (r) selected = r.id;
    refresh();
  });
  followStatus(ctx, (s) => JSON.stringify(s.runs), refresh);
  await refresh();
};

pages.data = async function (ctx) {
  const view = await loadMap($("#map"));
  const pick = $("#model-version");
  async function stats() {
    const s = await api("/api/v1/episodes/stats");
    const rejected = Object.values(s.rejected).reduce((a, b) => a + b, 0);
    $("#data-summary").replaceChildren(
      ...[
        ["episodes stored", s.stored],
        ["missions", s.missions],
        ["records rejected", rejected],
        ["records set aside", Object.values(s.set_aside || {}).reduce((a, b) => a + b, 0)],
        ["missions usable for training", s.usable_missions],
      ].flatMap(([k, v]) => [el("dt", {}, k), el("dd", { "data-fact": k }, v)]),
    );
    const byv = Object.entries(s.by_policy_version).sort((a, b) => Number(a[0]) - Number(b[0]));
    $("#by-version tbody").replaceChildren(...byv.map(([v, c]) => el("tr", {}, el("td", {}, v === "null" ? "—" : `v${v}`), el("td", {}, c))));
    const rej = Object.entries(s.rejected);
    $("#rejections tbody").replaceChildren(
      ...(rej.length ? rej.map(([k, c]) => el("tr", { "data-reason": k }, el("td", {}, k), el("td", {}, c))) : [el("tr", {}, el("td", { colspan: 2, class: "muted" }, "none"))]),
    );
    const aside = (await api("/api/v1/episodes?set_aside=true&limit=50")).items;
    $("#set-aside tbody").replaceChildren(
      ...(aside.length
        ? aside.map((e) => el("tr", { "data-mission": e.mission_id }, el("td", {}, `${e.robot_id} · ${e.mission_id}`), el("td", {}, e.set_aside)))
        : [el("tr", {}, el("td", { colspan: 2, class: "muted" }, "none"))]),
    );
  }
  async function model() {
    const m = await api(`/api/v1/policies/${pick.value}/model`);
    view.setHeat(m.stationary, (x) => `long-run probability ${x.toFixed(4)}`);
    const flows = [];
    let top = 0;
    for (const [u, v] of view.map.edges) {
      const w = (m.moves[u]?.[v] || 0) + (m.moves[v]?.[u] || 0);
      top = Math.max(top, w);
      flows.push([u, v, w]);
    }
    view.setFlows(flows.map(([u, v, w]) => [u, v, w / (top || 1)]));
    view.setRings(m.b0);
  }
  const list = await api("/api/v1/policies");
  pick.replaceChildren(...[...list.items].reverse().map((p) => el("option", { value: p.version }, `v${p.version}${p.current ? " (current)" : ""}`)));
  pick.value = String(list.current);
  pick.addEventListener("change", () => model().catch((e) => notice(e.message)));
  followStatus(ctx, (s) => JSON.stringify(s.episodes), stats);
  await Promise.all([stats(), model().catch((e) => notice(e.message))]);
};

// Each table cell carries its column's name (data-label), which a narrow screen shows beside the
// value when it stacks a table's rows as cards (console.css); kept up to date as tables refill.
function labelCells(root = document) {
  for (const table of root.querySelectorAll("table.grid")) {
    const names = [...table.querySelectorAll("thead th")].map((th) => th.textContent.trim());
    for (const tr of table.querySelectorAll("tbody tr")) {
      [...tr.children].forEach((td, i) => {
        if (names[i] && td.dataset.label !== names[i]) td.dataset.label = names[i];
      });
    }
  }
}
new MutationObserver(() => labelCells()).observe(document.documentElement, { childList: true, subtree: true });

// ------------------------------------------------------------------ start
async function start() {
  const page = document.body.dataset.page;
  if (page === "signin") return pages.signin();
  if (!sessionStorage.getItem(TOKEN_KEY)) return signOut("");
  const role = sessionStorage.getItem(ROLE_KEY) || "agent";
  const badge = $("#role");
  badge.textContent = role === "operator" ? "operator" : "read-only (agent token)";
  badge.className = `badge ${role}`;
  $("#signout").addEventListener("click", () => {
    sessionStorage.removeItem(TOKEN_KEY);
    sessionStorage.removeItem(ROLE_KEY);
    location.assign("/signin");
  });
  const ctx = { status: (s) => showAlerts(s.alerts) };
  try {
    await pages[page](ctx);
    document.body.dataset.ready = "1";
  } catch (e) {
    notice(`This page could not load: ${e.message}`);
  }
}

start();
