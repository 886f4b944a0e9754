/* mapserver web viewer: plain JavaScript, no dependencies, no build step.
 *
 * Everything shown comes from the REST API with the token kept in sessionStorage. The map page keeps
 * the last graph the server returned for a viewport (decimated to the zoom level's resolution) and
 * redraws it from memory on every pan or zoom frame; when the view settles it asks for the new box.
 */
"use strict";

const TOKEN_KEY = "mapserver-token";
const SESSION_COLOURS = ["#1f77b4", "#ff7f0e", "#2ca02c", "#9467bd", "#8c564b", "#e377c2", "#17becf", "#bcbd22"];
const LINK_STYLES = {
  odometry: { color: "#9e9e9e", width: 1, dash: [] },
  loop: { color: "#d62728", width: 1, dash: [] },
  merge: { color: "#6a1b9a", width: 2, dash: [6, 4] },
  manual: { color: "#00838f", width: 1.5, dash: [2, 2] },
  inactive: { color: "#cfcfcf", width: 1, dash: [1, 3] },
};
const PATH_COLOUR = "#00c853";
const MERGE_COLOUR = "#e91e63";
const MAX_NODES = 16000;

const $ = (sel) => document.querySelector(sel);
const el = (tag, attrs = {}, ...children) => {
  const node = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) {
    if (k === "class") node.className = v; else if (k.startsWith("on")) node.addEventListener(k.slice(2), v);
    else node.setAttribute(k, v);
  }
  for (const c of children) node.append(c instanceof Node ? c : document.createTextNode(String(c)));
  return node;
};
const fmt = (v, d = 3) => (v === null || v === undefined ? "–" : Number(v).toFixed(d));

/* ------------------------------------------------------------------ API and token */
function token() { return sessionStorage.getItem(TOKEN_KEY) || ""; }

function banner(text, ok = false) {
  const b = $("#banner");
  b.textContent = text; b.hidden = !text; b.className = ok ? "ok" : "";
}

async function api(path, opts = {}) {
  const headers = Object.assign({}, opts.headers || {});
  if (token()) headers.Authorization = "Bearer " + token();
  const resp = await fetch(path, Object.assign({}, opts, { headers }));
  if (!resp.ok) {
    let detail = resp.statusText;
    try { detail = (await resp.json()).detail || detail; } catch (e) { /* not JSON */ }
    if (resp.status === 401) detail += " — paste a token above";
    const err = new Error(`${resp.status}: ${detail}`); err.status = resp.status; throw err;
  }
  return opts.raw ? resp : resp.json();
}

function showToken() {
  $("#token-state").textContent = token() ? "token kept for this browser session" : "no token";
  $("#upload-hint").hidden = !!token();
}

// what the token may do (GET /v1/token): delete, rename and restore maps are shown to a write token only
let writeAccess = false;
async function refreshAccess() {
  let scope = null;
  if (token()) { try { scope = (await api("/v1/token")).scope; } catch (e) { scope = null; } }
  writeAccess = scope === "write";
  for (const node of document.querySelectorAll(".write-only")) node.hidden = !writeAccess;
  if (!writeAccess) $("#archived-list").hidden = true;
}

/* ------------------------------------------------------------------ routing */
function route() {
  const hash = decodeURIComponent(location.hash.replace(/^#/, "")) || "/";
  for (const id of ["maps-view", "map-view", "jobs-view"]) $("#" + id).hidden = true;
  banner("");
  if (hash.startsWith("/map/")) { $("#map-view").hidden = false; openMap(hash.slice(5)); }
  else if (hash === "/jobs") { $("#jobs-view").hidden = false; pollJobs(); }
  else { $("#maps-view").hidden = false; loadMaps(); }
}

/* ------------------------------------------------------------------ maps table */
const mapsState = { rows: [], key: "name", dir: 1 };

async function loadMaps() {
  try {
    const { maps } = await api("/v1/maps");
    const details = await Promise.all(maps.map((m) => api("/v1/maps/" + encodeURIComponent(m.name)).catch(() => ({}))));
    mapsState.rows = maps.map((m, i) => Object.assign({}, m, { updated_at: details[i].updated_at || "" }));
    renderMaps();
    renderIntoChoices(maps.map((m) => m.name));
    await loadArchived();
  } catch (err) { banner(err.message); }
}

// a map's health (GET /v1/maps): how well its active links agree, in words and a colour. A residual of
// 0.5–1.2 drifts expected over a link is consistent, a worst link over 3 is not (MapHealthPublic)
function healthGrade(h) {
  if (!h || typeof h.residual !== "number") return "none";
  if (h.unmeasured > 0 || h.residual > 2 || h.worst > 6) return "bad";
  return h.residual <= 1.2 && h.worst <= 3 ? "ok" : "warn";
}

function healthText(h) {
  if (!h || typeof h.residual !== "number") return "–";
  const words = { ok: "consistent", warn: "strained", bad: "inconsistent" }[healthGrade(h)];
  const off = h.switched_off ? `, ${h.switched_off} link${h.switched_off > 1 ? "s" : ""} off` : "";
  return `${words}: residual ${h.residual.toFixed(2)}, worst ${h.worst.toFixed(1)}${off}`;
}

const healthKey = (h) => (h && typeof h.residual === "number" ? h.residual : Infinity);

// log stamps (Unix seconds) as a local date and time, and a span as minutes and seconds
function when(stamp) {
  if (stamp === null || stamp === undefined) return "–";
  const d = new Date(stamp * 1000);
  return `${d.toLocaleDateString()} ${d.toLocaleTimeString([], { hour: "2-digit", minute: "2-digit" })}`;
}

function span(first, last) {
  if (first === null || first === undefined || last === null || last === undefined) return "–";
  const seconds = Math.max(0, Math.round(last - first));
  return seconds >= 60 ? `${Math.floor(seconds / 60)} min ${seconds % 60} s` : `${seconds} s`;
}

function renderMaps() {
  const { rows, key, dir } = mapsState;
  const sorted = rows.slice().sort((a, b) => {
    const x = key === "health" ? healthKey(a.health) : a[key], y = key === "health" ? healthKey(b.health) : b[key];
    return (x < y ? -1 : x > y ? 1 : 0) * dir;
  });
  const body = $("#maps-table tbody");
  body.replaceChildren(...sorted.map((m) => el("tr", { "data-map": m.name },
    el("td", {}, el("a", { href: "#/map/" + encodeURIComponent(m.name) }, m.name)),
    el("td", { class: "num" }, m.sessions), el("td", { class: "num" }, m.experiences),
    el("td", { class: "num" }, m.templates), el("td", { class: "num" }, m.links),
    el("td", { class: "health health-" + healthGrade(m.health) }, healthText(m.health)),
    el("td", {}, m.updated_at ? new Date(m.updated_at).toLocaleString() : "–"),
    ...(writeAccess ? [mapActions(m)] : []))));
  $("#maps-empty").hidden = rows.length > 0;
  for (const th of document.querySelectorAll("#maps-table th")) {
    th.classList.toggle("asc", th.dataset.key === key && dir === 1);
    th.classList.toggle("desc", th.dataset.key === key && dir === -1);
  }
}

/* ------------------------------------------------------------------ deleting, renaming, restoring maps */
// a modal question: resolves with the field's text (or true) when confirmed, null when cancelled; `act`
// runs on confirm and a failure it throws is shown in the dialog, which stays open
function ask({ title, text, ok, danger = false, field = null, act }) {
  return new Promise((resolve) => {
    const input = $("#dialog-input"), okButton = $("#dialog-ok");
    $("#dialog-title").textContent = title; $("#dialog-text").textContent = text; $("#dialog-error").textContent = "";
    $("#dialog-field").hidden = field === null; input.value = field || "";
    okButton.textContent = ok; okButton.className = danger ? "danger" : "";
    $("#dialog-backdrop").hidden = false;
    (field === null ? $("#dialog-cancel") : input).focus();
    const close = (value) => {
      $("#dialog-backdrop").hidden = true; okButton.onclick = null; $("#dialog-cancel").onclick = null;
      resolve(value);
    };
    $("#dialog-cancel").onclick = () => close(null);
    okButton.onclick = async () => {
      const value = field === null ? true : input.value.trim();
      try { await act(value); close(value); } catch (err) { $("#dialog-error").textContent = err.message; }
    };
  });
}

function mapActions(m) {
  return el("td", { class: "actions" },
    el("button", { class: "map-rename", type: "button", onclick: () => renameMap(m) }, "rename"),
    el("button", { class: "map-delete", type: "button", onclick: () => deleteMap(m) }, "delete"));
}

async function deleteMap(m) {
  const sessions = `${m.sessions} session${m.sessions === 1 ? "" : "s"}`;
  const done = await ask({
    title: `Delete map “${m.name}”?`,
    text: `The map leaves the list. It is archived, not destroyed: its ${sessions}, ${m.experiences} experiences ` +
      `and merge events are kept, and “show deleted maps” below restores it as it was.`,
    ok: "delete", danger: true,
    act: () => api("/v1/maps/" + encodeURIComponent(m.name), { method: "DELETE" }),
  });
  if (done) { banner(`map ${m.name} deleted (archived: it can be restored)`, true); await loadMaps(); }
}

async function renameMap(m) {
  const name = await ask({
    title: `Rename map “${m.name}”`,
    text: "1 to 64 characters from A-Z a-z 0-9 . _ -, starting with a letter or a digit.",
    ok: "rename", field: m.name,
    act: (value) => api("/v1/maps/" + encodeURIComponent(m.name), {
      method: "PATCH", headers: { "Content-Type": "application/json" }, body: JSON.stringify({ name: value }),
    }),
  });
  if (name) { banner(`map ${m.name} renamed to ${name}`, true); await loadMaps(); }
}

async function loadArchived() {
  const box = $("#archived-list");
  if (box.hidden) return;
  try {
    const { maps } = await api("/v1/maps?archived=true");
    $("#archived-table tbody").replaceChildren(...maps.map((m) => el("tr", { "data-map": m.name },
      el("td", {}, m.name), el("td", { class: "num" }, m.sessions), el("td", { class: "num" }, m.experiences),
      el("td", {}, m.archived_at ? new Date(m.archived_at).toLocaleString() : "–"),
      el("td", {}, el("button", { class: "map-restore", type: "button", onclick: () => restoreMap(m.name) }, "restore")))));
    $("#archived-empty").hidden = maps.length > 0;
  } catch (err) { banner(err.message); }
}

async function restoreMap(name) {
  try {
    await api("/v1/maps/" + encodeURIComponent(name) + "/restore", { method: "POST" });
    banner(`map ${name} restored`, true);
    await loadMaps();
  } catch (err) { banner(err.message); }
}

function toggleArchived() {
  const box = $("#archived-list");
  box.hidden = !box.hidden;
  $("#show-archived").textContent = box.hidden ? "show deleted maps" : "hide deleted maps";
  loadArchived();
}

/* ------------------------------------------------------------------ map page state */
const V = {
  name: null, map: null, view: "xy", data: null, cam: { cx: 0, cy: 0, scale: 1 }, selected: null,
  path: null, merge: null, pick: null, fetchTimer: null, drawPending: false, fetchSeq: 0,
};
window.viewerStats = { draws: [], sync: false, fetches: 0, lastDraw: null, pending: false };

function canvas() { return $("#graph"); }
function toScreen(x, y) {
  const c = canvas(), cam = V.cam;
  return [(x - cam.cx) * cam.scale + c.width / 2, c.height / 2 - (y - cam.cy) * cam.scale];
}
function toWorld(sx, sy) {
  const c = canvas(), cam = V.cam;
  return [(sx - c.width / 2) / cam.scale + cam.cx, (c.height / 2 - sy) / cam.scale + cam.cy];
}
function viewBox(margin = 0.5) {
  const c = canvas();
  const [x0, y1] = toWorld(-margin * c.width, -margin * c.height);
  const [x1, y0] = toWorld((1 + margin) * c.width, (1 + margin) * c.height);
  return [x0, y0, x1, y1];
}

async function openMap(name) {
  V.name = name; V.data = null; V.selected = null; V.path = null; V.merge = null; V.pick = null;
  V.truth = null;
  $("#map-title").textContent = name;
  $("#node-details").replaceChildren(); $("#path-result").replaceChildren();
  try {
    V.map = await api("/v1/maps/" + encodeURIComponent(name));
  } catch (err) { banner(err.message); return; }
  $("#map-info").textContent = `${V.map.sessions.length} sessions · ${V.map.experiences} experiences · ` +
    `${V.map.templates} templates · ${V.map.links} links · version ${V.map.version}`;
  await fetchGraph(null);
  renderSessions();
  fit();
  loadMerges();
  loadTruth();
}

async function fetchGraph(box) {
  const seq = ++V.fetchSeq;
  // finer than ~2 screen pixels would not show: the server refines its grid down to this cell size
  const q = new URLSearchParams({ max_nodes: MAX_NODES, view: V.view, resolution: (2 / V.cam.scale).toPrecision(4) });
  if (box) q.set("bbox", box.map((v) => v.toFixed(4)).join(","));
  try {
    const data = await api(`/v1/maps/${encodeURIComponent(V.name)}/graph?${q}`);
    if (seq !== V.fetchSeq) return;
    window.viewerStats.fetches += 1;
    if (box) window.viewerStats.pending = false;
    if (box) data.box = box;
    V.data = data;
    $("#lod").textContent = `${data.nodes.id.length} of ${data.in_view} nodes in view drawn` +
      (data.decimated ? ` (grid ${fmt(data.cell, 2)} m)` : "");
    renderLegend();
    requestDraw();
  } catch (err) { banner(err.message); }
}

function scheduleFetch() {
  clearTimeout(V.fetchTimer);
  window.viewerStats.pending = true;
  V.fetchTimer = setTimeout(() => fetchGraph(viewBox()), 200);
}

function fit() {
  if (!V.data) return;
  const [x0, y0, x1, y1] = V.data.bounds, c = canvas();
  const w = Math.max(x1 - x0, 1e-6), h = Math.max(y1 - y0, 1e-6);
  V.cam = { cx: (x0 + x1) / 2, cy: (y0 + y1) / 2, scale: 0.9 * Math.min(c.width / w, c.height / h) };
  requestDraw();
  if (V.data.decimated) scheduleFetch();
}

function renderLegend() {
  const items = [];
  (V.data ? V.data.sessions : []).forEach((s, i) => items.push(el("div", {},
    el("span", { class: "sw", style: `background:${SESSION_COLOURS[i % SESSION_COLOURS.length]}` }), s)));
  for (const [k, st] of Object.entries(LINK_STYLES)) {
    items.push(el("div", {}, el("span", { class: "ln", style: `border-top:2px ${st.dash.length ? "dashed" : "solid"} ${st.color}` }),
      k === "inactive" ? "switched off" : k));
  }
  $("#legend").replaceChildren(...items, ...legendExtras());
}

/* ------------------------------------------------------------------ drawing */
function requestDraw() {
  if (V.drawPending) return;
  V.drawPending = true;
  requestAnimationFrame(() => { V.drawPending = false; draw(); });
}

function drawLinks(ctx, d, xs, ys, w, h) {
  const L = d.links;
  const groups = {};
  for (let k = 0; k < L.a.length; k++) {
    const a = L.a[k], b = L.b[k];
    // cull links with both ends beyond the same edge of the canvas
    if ((xs[a] < 0 && xs[b] < 0) || (ys[a] < 0 && ys[b] < 0) || (xs[a] > w && xs[b] > w) || (ys[a] > h && ys[b] > h)) continue;
    const style = L.active[k] ? d.kinds[L.kind[k]] : "inactive";
    (groups[style] || (groups[style] = [])).push(k);
  }
  for (const [style, list] of linkLayers(groups)) {
    const st = LINK_STYLES[style] || LINK_STYLES.manual;
    ctx.strokeStyle = st.color; ctx.lineWidth = st.width; ctx.setLineDash(st.dash);
    ctx.beginPath();
    for (const k of list) { ctx.moveTo(xs[L.a[k]], ys[L.a[k]]); ctx.lineTo(xs[L.b[k]], ys[L.b[k]]); }
    ctx.stroke();
  }
  ctx.setLineDash([]);
}

function drawNodes(ctx, d, xs, ys, w, h) {
  const n = d.nodes.id.length;
  const size = n > 5000 ? 2 : n > 500 ? 4 : 6, half = size / 2;
  const bySession = d.sessions.map(() => []);
  for (let i = 0; i < n; i++) {
    if (xs[i] < -half || ys[i] < -half || xs[i] > w + half || ys[i] > h + half) continue;
    bySession[d.nodes.session[i]].push(i);
  }
  bySession.forEach((list, s) => {
    ctx.fillStyle = SESSION_COLOURS[s % SESSION_COLOURS.length];
    for (const i of list) ctx.fillRect(Math.round(xs[i] - half), Math.round(ys[i] - half), size, size);
  });
}

function drawOverlays(ctx) {
  if (V.merge) {
    ctx.strokeStyle = MERGE_COLOUR; ctx.lineWidth = 2;
    for (const place of V.merge.places) {
      const here = place.nodes.filter((n) => n.map === V.name);
      const pts = here.map((n) => toScreen(n.x, V.view === "xz" ? n.z : n.y));
      for (const [sx, sy] of pts) { ctx.beginPath(); ctx.arc(sx, sy, 8, 0, 2 * Math.PI); ctx.stroke(); }
      for (let i = 1; i < here.length; i++) { // join the place's experiences across sessions
        if (here[i].session === here[0].session) continue;
        ctx.beginPath(); ctx.moveTo(...pts[0]); ctx.lineTo(...pts[i]); ctx.stroke();
      }
    }
  }
  if (V.path) {
    ctx.strokeStyle = PATH_COLOUR; ctx.lineWidth = 4; ctx.lineJoin = "round";
    ctx.beginPath();
    V.path.poses.forEach((p, i) => {
      const [sx, sy] = toScreen(p.x, V.view === "xz" ? p.z : p.y);
      if (i === 0) ctx.moveTo(sx, sy); else ctx.lineTo(sx, sy);
    });
    ctx.stroke();
  }
  if (V.selected) {
    const [sx, sy] = toScreen(V.selected.x, V.view === "xz" ? V.selected.z : V.selected.y);
    ctx.strokeStyle = "#000"; ctx.lineWidth = 2;
    ctx.beginPath(); ctx.arc(sx, sy, 10, 0, 2 * Math.PI); ctx.stroke();
  }
}

function drawScale(ctx, w, h) {
  const target = 100 / V.cam.scale, p = Math.pow(10, Math.floor(Math.log10(target)));
  const len = [1, 2, 5, 10].map((m) => m * p).find((v) => v >= target) || target;
  const px = len * V.cam.scale;
  ctx.strokeStyle = "#333"; ctx.lineWidth = 2;
  ctx.beginPath(); ctx.moveTo(w - 20 - px, h - 20); ctx.lineTo(w - 20, h - 20); ctx.stroke();
  ctx.fillStyle = "#333"; ctx.font = "12px sans-serif";
  ctx.fillText(`${len >= 1 ? len : len.toPrecision(1)} m`, w - 20 - px, h - 26);
}

function draw() {
  const t0 = performance.now();
  const c = canvas(), ctx = c.getContext("2d");
  const w = c.width, h = c.height;
  ctx.clearRect(0, 0, w, h);
  const d = V.data;
  if (d) {
    const n = d.nodes.id.length, xs = new Float64Array(n), ys = new Float64Array(n);
    const cam = V.cam, ox = w / 2 - cam.cx * cam.scale, oy = h / 2 + cam.cy * cam.scale;
    for (let i = 0; i < n; i++) { xs[i] = d.nodes.x[i] * cam.scale + ox; ys[i] = oy - d.nodes.y[i] * cam.scale; }
    drawTruth(ctx);
    drawLinks(ctx, d, xs, ys, w, h);
    drawNodes(ctx, d, xs, ys, w, h);
    drawOverlays(ctx);
    drawEnds(ctx, d);
    drawScale(ctx, w, h);
  }
  if (window.viewerStats.sync) ctx.getImageData(0, 0, 1, 1); // wait for the raster (measurement)
  const ms = performance.now() - t0;
  window.viewerStats.lastDraw = ms;
  window.viewerStats.draws.push(ms);
  if (window.viewerStats.draws.length > 1000) window.viewerStats.draws.shift();
}

/* ------------------------------------------------------------------ interaction */
function setupCanvas() {
  const c = canvas();
  let drag = null;
  c.addEventListener("pointerdown", (e) => {
    drag = { x: e.offsetX, y: e.offsetY, cx: V.cam.cx, cy: V.cam.cy, moved: false };
    c.setPointerCapture(e.pointerId);
  });
  c.addEventListener("pointermove", (e) => {
    if (!drag) return;
    const dx = e.offsetX - drag.x, dy = e.offsetY - drag.y;
    if (Math.abs(dx) + Math.abs(dy) > 3) drag.moved = true;
    V.cam.cx = drag.cx - dx / V.cam.scale; V.cam.cy = drag.cy + dy / V.cam.scale;
    requestDraw();
  });
  c.addEventListener("pointerup", (e) => {
    const was = drag; drag = null;
    if (!was) return;
    if (was.moved) scheduleFetch(); else clickAt(e.offsetX, e.offsetY);
  });
  c.addEventListener("wheel", (e) => {
    e.preventDefault();
    const [wx, wy] = toWorld(e.offsetX, e.offsetY);
    const f = Math.exp(-e.deltaY * 0.0015);
    V.cam.scale *= f;
    V.cam.cx = wx - (wx - V.cam.cx) / f; V.cam.cy = wy - (wy - V.cam.cy) / f;
    requestDraw(); scheduleFetch();
  }, { passive: false });
}

async function clickAt(sx, sy) {
  const [x, y] = toWorld(sx, sy);
  try {
    const q = new URLSearchParams({ x, y, view: V.view });
    const found = await api(`/v1/maps/${encodeURIComponent(V.name)}/nearest?${q}`);
    if (found.distance * V.cam.scale > 25) return; // nothing near the click
    if (V.pick) {
      $(V.pick === "from" ? "#path-from" : "#path-to").value = found.id;
      $("#pick-" + V.pick).classList.remove("picking");
      V.pick = null;
      return;
    }
    await showNode(found.id);
  } catch (err) { banner(err.message); }
}

async function showNode(id) {
  const base = `/v1/maps/${encodeURIComponent(V.name)}/experiences/${id}`;
  const node = await api(base);
  V.selected = node; requestDraw();
  selectTab("node");
  const rows = [["id", node.id], ["session", node.session], ["stamp", fmt(node.stamp, 3) + " s"],
    ["x, y, z", `${fmt(node.x)}, ${fmt(node.y)}, ${fmt(node.z)} m`], ["yaw", fmt(node.yaw) + " rad"],
    ["template", `${node.template} (${node.template_new ? "new here" : "recognised"})`]];
  const img = el("img", { id: "evidence", alt: "no evidence image" });
  const box = $("#node-details");
  box.replaceChildren(img, el("table", {}, ...rows.map(([k, v]) => el("tr", {}, el("th", {}, k), el("td", {}, v)))),
    el("h3", {}, "links"),
    el("table", { id: "node-links" }, ...node.links.map((l) => el("tr", { class: "link-" + l.kind },
      el("td", {}, l.kind + (l.active ? "" : " (off)")), el("td", {}, `${l.from} → ${l.to}`),
      el("td", {}, fmt(l.distance, 2) + " m"), el("td", {}, fmt(l.dt, 2) + " s")))));
  try {
    const resp = await api(base + "/evidence", { raw: true });
    img.src = URL.createObjectURL(await resp.blob());
  } catch (err) { img.replaceWith(el("p", { class: "hint", id: "no-evidence" }, "no evidence image: " + err.message)); }
}

async function findPath() {
  const from = $("#path-from").value, to = $("#path-to").value, weight = $("#path-weight").value;
  const out = $("#path-result");
  if (from === "" || to === "") { out.textContent = "choose two nodes"; return; }
  try {
    const q = new URLSearchParams({ from, to, weight });
    V.path = await api(`/v1/maps/${encodeURIComponent(V.name)}/path?${q}`);
    const unit = weight === "time" ? "s" : "m";
    out.replaceChildren(el("p", { id: "path-cost" }, `cost ${fmt(V.path.cost, 2)} ${unit} (${weight}), ` +
      `${V.path.nodes.length} nodes`), el("p", { class: "hint" }, V.path.nodes.join(" → ")));
  } catch (err) { V.path = null; out.textContent = err.message; }
  requestDraw();
}

/* ------------------------------------------------------------------ merges and sessions */
async function loadMerges() {
  const box = $("#merge-list");
  try {
    const { merges } = await api("/v1/merges?map=" + encodeURIComponent(V.name));
    if (!merges.length) { box.replaceChildren(el("p", { class: "hint" }, "no merge events")); return; }
    box.replaceChildren(...merges.map(mergeItem));
  } catch (err) { box.textContent = err.message; }
}

function mergeItem(m) {
  const t = m.transform;
  const sessions = Object.entries(m.sessions).map(([s, r]) => `${s} (${r})`).join(", ");
  const item = el("div", { class: "merge", "data-event": m.id },
    el("div", {}, `#${m.id} `, el("span", { class: "status-" + m.status }, m.status), ` · ${m.mode} · ${m.confirmations} confirmations`),
    el("div", {}, sessions),
    el("div", {}, `transform t = (${fmt(t[0], 2)}, ${fmt(t[1], 2)}, ${fmt(t[2], 2)}) m, yaw ${fmt(m.yaw * 180 / Math.PI, 1)}°`),
    el("div", {}, `${m.places.length} matched places`),
    m.reason ? el("div", { class: "hint" }, String(m.reason)) : "",
    m.link ? el("div", {}, `manual link ${m.link.from} → ${m.link.to} by ${m.link.author}` +
                           (m.link.active ? "" : " · flagged: it contradicts the map, switched off")) : "");
  const buttons = el("div", {}, el("button", { class: "show", onclick: () => showMerge(m, item) }, "show on map"));
  if (m.status === "applied") buttons.append(el("button", { class: "undo", onclick: () => mergeAction(m.id, "undo") }, "undo"));
  if (m.status === "undone") buttons.append(el("button", { class: "redo", onclick: () => mergeAction(m.id, "redo") }, "redo"));
  item.append(buttons);
  return item;
}

function showMerge(m, item) {
  V.merge = m;
  for (const x of document.querySelectorAll(".merge")) x.classList.remove("shown");
  item.classList.add("shown");
  requestDraw();
}

async function mergeAction(id, action) {
  try {
    const res = await api(`/v1/merges/${id}/${action}`, { method: "POST" });
    banner(`merge #${id}: ${res.status} (maps ${res.maps.join(", ")})`, true);
    const stay = V.name;
    try { await api("/v1/maps/" + encodeURIComponent(stay)); await openMap(stay); }
    catch (e) { location.hash = "#/"; }
  } catch (err) { banner(err.message); }
}

function renderSessions() {
  const rows = V.map.sessions.map((s, i) => {
    const k = V.data && V.data.sessions.includes(s.name) ? V.data.sessions.indexOf(s.name) : i;
    return el("tr", {},
    el("td", {}, el("span", { class: "sw", style: `display:inline-block;width:10px;height:10px;background:${SESSION_COLOURS[k % SESSION_COLOURS.length]}` })),
    el("td", {}, s.name, el("br"), el("small", {}, s.status)),
    el("td", { class: "num" }, s.frames, el("br"), el("small", {}, s.frames_per_s ? `${Math.round(s.frames_per_s)}/s` : "")),
    el("td", { class: "when" }, when(s.first_stamp), el("br"), el("small", {}, span(s.first_stamp, s.last_stamp))));
  });
  $("#session-list").replaceChildren(el("table", {}, el("tr", {}, el("th", {}, ""), el("th", {}, "session"),
    el("th", {}, "frames"), el("th", {}, "recorded")), ...rows));
}

function selectTab(name) {
  for (const b of document.querySelectorAll(".tabs button")) b.classList.toggle("on", b.dataset.tab === name);
  for (const t of document.querySelectorAll(".tab")) t.hidden = t.id !== "tab-" + name;
}

/* ------------------------------------------------------------------ link layers, trajectory ends, ground truth */
// links are stroked kind by kind in this order, so loop closures and merges lie above the odometry chain
const LINK_ORDER = ["inactive", "odometry", "manual", "merge", "loop"];
const TRUTH_STYLE = { color: "#212121", width: 2, dash: [6, 4] };
const END_OUTLINE = "#000000";

function linkLayers(groups) {
  const rank = (k) => (LINK_ORDER.includes(k) ? LINK_ORDER.indexOf(k) : LINK_ORDER.length);
  const layers = Object.entries(groups).sort((a, b) => rank(a[0]) - rank(b[0]));
  window.viewerStats.linkOrder = layers.map(([k]) => k);
  return layers;
}

// each session's first and last experience (data.ends, over the whole map) and the path's two ends:
// a circle where a trajectory starts, a square where it ends, filled with its colour, outlined in black
function endMarkers(d) {
  const marks = [];
  for (const e of d.ends || []) {
    const colour = SESSION_COLOURS[e.session % SESSION_COLOURS.length];
    marks.push({ kind: "start", session: d.sessions[e.session], id: e.start.id, x: e.start.x, y: e.start.y, colour });
    marks.push({ kind: "end", session: d.sessions[e.session], id: e.end.id, x: e.end.x, y: e.end.y, colour });
  }
  if (V.path && V.path.poses.length) {
    const ends = [["start", V.path.poses[0], V.path.nodes[0]], ["end", V.path.poses[V.path.poses.length - 1], V.path.nodes[V.path.nodes.length - 1]]];
    for (const [kind, p, id] of ends) marks.push({ kind, session: null, id, x: p.x, y: V.view === "xz" ? p.z : p.y, colour: PATH_COLOUR });
  }
  return marks;
}

function drawMarker(ctx, kind, sx, sy, colour) {
  ctx.fillStyle = colour; ctx.strokeStyle = END_OUTLINE; ctx.lineWidth = 2; ctx.setLineDash([]);
  ctx.beginPath();
  if (kind === "start") ctx.arc(sx, sy, 7, 0, 2 * Math.PI); else ctx.rect(sx - 6.5, sy - 6.5, 13, 13);
  ctx.fill(); ctx.stroke();
}

function drawEnds(ctx, d) {
  const marks = endMarkers(d);
  for (const m of marks) { const [sx, sy] = toScreen(m.x, m.y); drawMarker(ctx, m.kind, sx, sy, m.colour); m.sx = sx; m.sy = sy; }
  window.viewerStats.markers = marks;
}

function drawTruth(ctx) {
  if (!V.truth || !V.truthShown) { window.viewerStats.truthDrawn = 0; return; }
  ctx.strokeStyle = TRUTH_STYLE.color; ctx.lineWidth = TRUTH_STYLE.width; ctx.setLineDash(TRUTH_STYLE.dash);
  ctx.lineJoin = "round";
  let drawn = 0;
  for (const s of V.truth.sessions) {
    ctx.beginPath();
    for (let i = 0; i < s.x.length; i++) {
      const [sx, sy] = toScreen(s.x[i], s.y[i]);
      if (i === 0) ctx.moveTo(sx, sy); else ctx.lineTo(sx, sy);
    }
    ctx.stroke();
    drawn += s.x.length;
  }
  ctx.setLineDash([]);
  window.viewerStats.truthDrawn = drawn;
}

function legendExtras() {
  const shape = (kind) => {
    const c = el("canvas", { width: "16", height: "16", class: "mk" });
    drawMarker(c.getContext("2d"), kind, 8, 8, "#ffffff");
    return c;
  };
  const items = [el("div", { class: "lg-start" }, shape("start"), "start"), el("div", { class: "lg-end" }, shape("end"), "end")];
  if (V.truth && V.truth.sessions.length) {
    items.push(el("div", { class: "lg-truth" },
      el("span", { class: "ln", style: `border-top:2px dashed ${TRUTH_STYLE.color}` }), "ground truth"));
  }
  return items;
}

// GET …/ground-truth: the sessions' stored ground truth in the map's frame and each one's APE (as
// `mapserver evaluate --session` gives it); the toggle shows only when a session has ground truth
async function loadTruth() {
  const name = V.name;
  V.truth = null;
  $("#truth-toggle").hidden = true;
  try {
    const q = new URLSearchParams({ view: V.view, limit: 5000 });
    const truth = await api(`/v1/maps/${encodeURIComponent(name)}/ground-truth?${q}`);
    if (name !== V.name) return;
    V.truth = truth;
  } catch (err) { if (name === V.name) $("#truth-list").textContent = err.message; return; }
  $("#truth-toggle").hidden = V.truth.sessions.length === 0;
  renderTruth(); renderLegend(); requestDraw();
}

function renderTruth() {
  const t = V.truth, box = $("#truth-list");
  if (!t.sessions.length) {
    box.replaceChildren(el("p", { class: "hint", id: "truth-none" }, "No session of this map has ground truth " +
      "(a log with a ground-truth topic keeps it; mapserver ground-truth adds it to a stored session)."));
    return;
  }
  const rows = t.sessions.map((s) => el("tr", { "data-session": s.name },
    el("td", {}, s.name),
    s.ape ? el("td", { class: "num ape" }, `${fmt(s.ape.ape_rmse, 3)} m`) : el("td", { class: "hint" }, s.error),
    el("td", { class: "num" }, s.ape ? `${s.ape.aligned} / ${s.ape.experiences}` : "–"),
    el("td", { class: "num" }, s.ape ? `${fmt(s.ape.hausdorff, 2)} m` : "–")));
  for (const n of t.without) rows.push(el("tr", { "data-session": n }, el("td", {}, n), el("td", { class: "hint" }, "no ground truth"), el("td", {}, ""), el("td", {}, "")));
  box.replaceChildren(el("table", { id: "truth-table" }, el("tr", {}, el("th", {}, "session"), el("th", {}, "APE RMSE"),
    el("th", {}, "aligned"), el("th", {}, "Hausdorff")), ...rows),
    el("p", { class: "hint" }, "As mapserver evaluate --session gives it: the session's experiences aligned rigidly " +
      "to its ground truth (Umeyama), the RMSE of their position errors."));
}

/* ------------------------------------------------------------------ uploads and jobs */
// the upload form's "into" choice: the live maps; choosing one merges the log into it (POST /v1/sessions into=)
function renderIntoChoices(names) {
  const select = $("#upload-into");
  const chosen = select.value;
  select.replaceChildren(el("option", { value: "" }, "(a new map, or wherever it merges)"),
    ...names.map((n) => el("option", { value: n }, n)));
  select.value = names.includes(chosen) ? chosen : "";
  intoChanged();
}

function intoChanged() {
  const into = $("#upload-into").value !== "";
  $("#upload-map").disabled = into;  // a name is for a new map: with "into" the log joins an existing one
  $("#upload-merge").disabled = into;
}

let jobList = [];  // the newest jobs as GET /v1/jobs lists them: sent from this tab, another one, or curl
let queuedBanner = null;  // the job whose "queued" banner shows, cleared when it ends

async function upload(e) {
  e.preventDefault();
  const file = $("#upload-file").files[0];
  if (!file) return;
  const form = new FormData();
  form.append("file", file, file.name);
  form.append("preset", $("#upload-preset").value);
  const into = $("#upload-into").value;
  if (into) form.append("into", into);  // merge into that map, or be refused before the job starts
  else if ($("#upload-map").value) form.append("map", $("#upload-map").value);
  form.append("merge", into || $("#upload-merge").checked ? "true" : "false");
  try {
    const res = await api("/v1/sessions", { method: "POST", body: form });
    banner(`job ${res.job} ${res.duplicate ? "(already uploaded)" : "queued"}`, true);
    queuedBanner = res.job;
    pollJobs();
  } catch (err) { banner(err.message); }
}

let polling = null;
async function pollJobs() {
  clearTimeout(polling);
  try { jobList = (await api("/v1/jobs?limit=50")).jobs; } catch (err) { banner(err.message); return; }
  renderJobs();
  const ended = jobList.find((j) => j.job === queuedBanner && (j.status === "done" || j.status === "failed"));
  if (ended) { banner(`job ${ended.job} ${ended.status}`, ended.status === "done"); queuedBanner = null; }
  const open = jobList.some((j) => j.status === "queued" || j.status === "running");
  if (open && !$("#jobs-view").hidden) polling = setTimeout(pollJobs, 400);
}

function renderJobs() {
  $("#jobs-table tbody").replaceChildren(...jobList.map((j) => el("tr", { "data-job": j.job, class: "job-" + j.status },
    el("td", {}, j.job), el("td", {}, j.upload || ""), el("td", { class: "status" }, j.status),
    el("td", {}, el("progress", { max: "1", value: String(j.progress || 0) }), ` ${Math.round(100 * (j.progress || 0))} %`),
    el("td", {}, j.session || ""),
    el("td", {}, j.map ? el("a", { href: "#/map/" + encodeURIComponent(j.map) }, j.map) : ""),
    el("td", {}, j.error || ""))));
}

/* ------------------------------------------------------------------ start */
function start() {
  showToken();
  $("#token-form").addEventListener("submit", (e) => {
    e.preventDefault();
    sessionStorage.setItem(TOKEN_KEY, $("#token").value.trim()); $("#token").value = "";
    showToken(); refreshAccess().then(route);
  });
  $("#token-clear").addEventListener("click", () => {
    sessionStorage.removeItem(TOKEN_KEY); showToken(); refreshAccess().then(route);
  });
  $("#show-archived").addEventListener("click", toggleArchived);
  for (const th of document.querySelectorAll("#maps-table th[data-key]")) {
    th.addEventListener("click", () => {
      mapsState.dir = mapsState.key === th.dataset.key ? -mapsState.dir : 1;
      mapsState.key = th.dataset.key; renderMaps();
    });
  }
  for (const b of document.querySelectorAll(".tabs button")) b.addEventListener("click", () => selectTab(b.dataset.tab));
  $("#view-select").addEventListener("change", async (e) => { V.view = e.target.value; await fetchGraph(null); fit(); loadTruth(); });
  $("#truth-show").addEventListener("change", (e) => { V.truthShown = e.target.checked; requestDraw(); });
  $("#fit").addEventListener("click", fit);
  for (const which of ["from", "to"]) {
    $("#pick-" + which).addEventListener("click", (e) => { V.pick = which; e.target.classList.add("picking"); });
  }
  $("#path-go").addEventListener("click", findPath);
  $("#upload-form").addEventListener("submit", upload);
  $("#upload-into").addEventListener("change", intoChanged);
  setupCanvas();
  window.addEventListener("hashchange", route);
  refreshAccess().then(route);
}

window.viewer = { V, draw, fit, showNode, findPath, toScreen, fetchGraph, viewBox };
start();
