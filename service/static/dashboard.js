// PipeSentry dashboard: a static page over the operator API (no build step, no CDN).
// The API key comes from the form (kept in localStorage) or once from the URL fragment
// (#key=...), which browsers never send to the server, so it stays out of access logs.
"use strict";

const API = document.querySelector('meta[name="pipesentry-api-base"]').content;
const REFRESH_MS = 1000 * Number(document.querySelector('meta[name="pipesentry-refresh-s"]').content || "10");
const KEY_STORAGE = "pipesentry.apiKey";
const TREND_POINTS = 100;
const PAGE_SIZE = 100; // table rows per page of /fleet/nodes
const CARD_ALL_UP_TO = 24; // a fleet this small gets a card per node; a larger one only for its flagged ones
const MAX_CARDS = 12; // ...of the page shown, at most this many (each card loads a trend and a map)
const SVG_NS = "http://www.w3.org/2000/svg";

const shownMaps = new Map(); // node_id -> measurement id whose heatmap is displayed
let timer = null;
const view = { site: "", state: "", cursor: null, cursors: [] }; // the page of nodes shown, and the way back

class Unauthorized extends Error {}

function apiKey() { return localStorage.getItem(KEY_STORAGE); }

function takeKeyFromFragment() {
  const match = /(?:^|&)key=([^&]+)/.exec(location.hash.slice(1));
  if (match) {
    localStorage.setItem(KEY_STORAGE, decodeURIComponent(match[1]));
    history.replaceState(null, "", location.pathname + location.search);
  }
}

async function api(path, as = "json") {
  const response = await fetch(API + path, { headers: { Authorization: "Bearer " + apiKey() }, cache: "no-store" });
  if (response.status === 401) throw new Unauthorized("the API key was refused");
  if (!response.ok) {
    let detail = response.statusText;
    try { detail = (await response.json()).detail || detail; } catch (_) { /* not a problem document */ }
    const error = new Error(detail);
    error.status = response.status;
    throw error;
  }
  return as === "blob" ? response.blob() : response.json();
}

function el(tag, attrs = {}, ...children) {
  const node = document.createElement(tag);
  for (const [name, value] of Object.entries(attrs)) {
    if (name === "class") node.className = value; else node.setAttribute(name, value);
  }
  for (const child of children) node.append(child instanceof Node ? child : document.createTextNode(String(child)));
  return node;
}

function fmt(value, digits = 3) {
  return value === null || value === undefined ? "–" : String(Number(Number(value).toPrecision(digits)));
}
function when(iso) { return iso ? new Date(iso).toLocaleString() : "–"; }
// A configured node that has never answered: offline since the gateway started watching it.
function seenText(health) {
  return health.never_seen ? `never (watched since ${when(health.watched_since)})` : when(health.last_seen_at);
}
function onlineText(health) { return health.online ? "yes" : health.never_seen ? "never seen" : "offline"; }
function stateBadge(state) { return el("span", { class: "state state-" + state, "data-state": state }, state.replaceAll("_", " ")); }

function showKeyForm(message) {
  clearTimeout(timer);
  document.getElementById("key-form").hidden = false;
  document.getElementById("fleet").hidden = true;
  document.getElementById("sites").hidden = true;
  document.getElementById("forget-key").hidden = true;
  document.getElementById("nodes").replaceChildren();
  shownMaps.clear();
  const error = document.getElementById("key-error");
  error.hidden = !message;
  error.textContent = message || "";
  document.getElementById("status").textContent = "API key needed";
}

function siteName(site) { return site === null ? "this gateway" : site; }

function renderSites(sites) {
  const rows = sites.map((s) => {
    const row = el("tr", { "data-site": s.site === null ? "" : s.site, class: s.flagged ? "flagged" : "" },
      el("td", {}, siteName(s.site)),
      el("td", {}, s.gateways.join(", ") || "–"),
      el("td", {}, String(s.nodes)),
      el("td", {}, `${s.by_state.damage || 0} / ${s.by_state.suspected || 0}`),
      el("td", s.offline ? { class: "offline" } : {}, String(s.offline)),
      el("td", {}, when(s.last_seen_at)));
    if (s.site !== null) row.addEventListener("click", () => { setFilter("site", s.site); });
    return row;
  });
  document.querySelector("#sites-table tbody").replaceChildren(...rows);
  document.getElementById("sites").hidden = false;
  const select = document.getElementById("site-filter");
  const named = sites.filter((s) => s.site !== null).map((s) => s.site).sort();
  select.replaceChildren(el("option", { value: "" }, "all sites"), ...named.map((name) => el("option", { value: name }, name)));
  select.value = view.site;
}

function setFilter(which, value) {
  view[which] = value;
  view.cursor = null;
  view.cursors = [];
  document.getElementById(which + "-filter").value = value;
  refresh();
}

function renderFleet(nodes) {
  const rows = nodes.map((n) => el("tr", { "data-node": n.node_id },
    el("td", { title: n.details.location || "" }, n.details.label ? `${n.details.label} (${n.node_id})` : n.node_id),
    el("td", {}, n.site === null ? "–" : `${n.site} / ${n.gateway_id}`),
    el("td", {}, stateBadge(n.state)),
    el("td", {}, when(n.state_since)),
    el("td", n.health.online ? {} : { class: "offline" }, onlineText(n.health)),
    el("td", {}, seenText(n.health)),
    el("td", {}, `${fmt(n.latest_di_peak)} / ${fmt(n.latest_threshold)}`),
    el("td", {}, n.active_baseline ? `measurement ${n.active_baseline.measurement_id} (${n.active_baseline.created_by})` : "none"),
  ));
  document.querySelector("#fleet-table tbody").replaceChildren(...rows);
}

function card(nodeId) {
  let section = document.querySelector(`.node-card[data-node="${CSS.escape(nodeId)}"]`);
  if (!section) {
    section = el("article", { class: "node-card", "data-node": nodeId },
      el("h3", {}, el("span", { class: "name" }, nodeId), el("span", { class: "badge" })),
      el("p", { class: "meta summary" }),
      el("p", { class: "notice", hidden: "" }),
      el("img", { class: "heatmap", alt: `latest DI map of ${nodeId}` }),
      el("p", { class: "estimate", hidden: "" }),
      el("p", { class: "meta map-caption" }),
      svg("svg", { class: "trend", viewBox: "0 0 560 170", role: "img", "aria-label": `DI peak trend of ${nodeId}` }),
      el("p", { class: "meta baseline" }));
    document.getElementById("nodes").append(section);
  }
  return section;
}

function svg(tag, attrs = {}) {
  const node = document.createElementNS(SVG_NS, tag);
  for (const [name, value] of Object.entries(attrs)) node.setAttribute(name, value);
  return node;
}

// "Nice" axis steps: 1, 2 or 5 times a power of ten, about `count` of them over the range.
function niceStep(span, count) {
  const raw = span / Math.max(1, count);
  const power = 10 ** Math.floor(Math.log10(raw));
  return [1, 2, 5, 10].map((m) => m * power).find((step) => step >= raw);
}

const TIME_STEPS_S = [1, 2, 5, 10, 15, 30, 60, 120, 300, 600, 900, 1800, 3600, 2 * 3600, 6 * 3600, 12 * 3600, 86400, 7 * 86400];

function timeLabel(ms, stepS) {
  const d = new Date(ms);
  if (stepS >= 86400) return d.toLocaleDateString([], { month: "short", day: "numeric" });
  if (stepS < 60) return d.toLocaleTimeString([], { hour: "2-digit", minute: "2-digit", second: "2-digit" });
  return d.toLocaleTimeString([], { hour: "2-digit", minute: "2-digit" });
}

function svgText(target, attrs, text) {
  const node = svg("text", attrs);
  node.textContent = text;
  target.append(node);
}

// The DI peak over time against the threshold: a time axis, nice DI ticks, the threshold as a step
// line that holds until it changes (so one calibrated reading already draws it), exceedances in red.
function drawTrend(target, detections, currentThreshold) {
  const points = detections.slice().reverse().map((d) => ({ ...d, t: Date.parse(d.created_at) })); // oldest first
  const width = 560, height = 170, left = 52, right = 12, top = 10, bottom = 34;
  target.replaceChildren();
  const values = points.flatMap((d) => [d.peak_di, d.threshold]).concat([currentThreshold])
    .filter((v) => v !== null && v !== undefined);
  if (points.length === 0 || values.length === 0) {
    svgText(target, { x: left, y: height / 2, class: "axis" }, "no monitor measurements yet");
    return;
  }
  // The axis runs a little past the last reading: the threshold holds on, so a single calibrated
  // reading already draws a line, and the latest point is not squeezed against the edge.
  const tLast = Math.max(points[points.length - 1].t, points[0].t + 1000);
  const t0 = points[0].t, t1 = tLast + 0.06 * (tLast - points[0].t);
  const yStep = niceStep(Math.max(...values) * 1.15 || 1, 4);
  const hi = Math.ceil((Math.max(...values) * 1.15 || 1) / yStep) * yStep;
  const x = (t) => left + ((t - t0) * (width - left - right)) / (t1 - t0);
  const y = (v) => top + (height - top - bottom) * (1 - v / hi);
  const digits = Math.max(0, -Math.floor(Math.log10(yStep)));
  for (let v = 0; v <= hi + yStep / 2; v += yStep) {  // DI ticks and grid lines
    target.append(svg("line", { class: "grid", x1: left, x2: width - right, y1: y(v), y2: y(v) }));
    svgText(target, { x: left - 4, y: y(v) + 3, class: "axis tick-di", "text-anchor": "end" }, v.toFixed(digits));
  }
  const spanS = (t1 - t0) / 1000;
  const tStep = (TIME_STEPS_S.find((s) => spanS / s <= 6) || TIME_STEPS_S[TIME_STEPS_S.length - 1]) * 1000;
  for (let t = Math.ceil(t0 / tStep) * tStep; t <= tLast; t += tStep) {  // time ticks
    target.append(svg("line", { class: "axis-line", x1: x(t), x2: x(t), y1: height - bottom, y2: height - bottom + 4 }));
    svgText(target, { x: x(t), y: height - bottom + 14, class: "axis tick-time", "text-anchor": "middle" },
      timeLabel(t, tStep / 1000));
  }
  target.append(svg("line", { class: "axis-line", x1: left, x2: width - right, y1: height - bottom, y2: height - bottom }));
  const steps = [];
  points.forEach((d, i) => {
    if (d.threshold === null || d.threshold === undefined) return;
    const until = i + 1 < points.length ? points[i + 1].t : t1;
    steps.push(`${x(d.t)},${y(d.threshold)}`, `${x(until)},${y(d.threshold)}`);
  });
  if (steps.length) {
    target.append(svg("polyline", { class: "threshold", fill: "none", points: steps.join(" ") }));
    const last = points.filter((d) => d.threshold !== null && d.threshold !== undefined).pop();
    svgText(target, { x: width - right, y: y(last.threshold) - 4, class: "axis threshold-label", "text-anchor": "end" },
      `threshold ${fmt(last.threshold)}`);
  }
  const withPeak = points.filter((d) => d.peak_di !== null && d.peak_di !== undefined);
  target.append(svg("polyline", { class: "peak", points: withPeak.map((d) => `${x(d.t)},${y(d.peak_di)}`).join(" ") }));
  for (const d of withPeak) {
    if (d.threshold !== null && d.threshold !== undefined && d.peak_di > d.threshold) {
      target.append(svg("circle", { class: "exceedance", cx: x(d.t), cy: y(d.peak_di), r: 2.5 }));
    }
  }
  svgText(target, { x: left, y: height - 4, class: "axis" },
    `DI peak (blue; red: above the threshold) and threshold (dashed), last ${points.length} measurements`);
}

async function renderNode(node) {
  const section = card(node.node_id);
  for (const state of ["damage", "suspected", "no_valid_baseline"]) section.classList.toggle(state, node.state === state);
  section.querySelector(".badge").replaceChildren(stateBadge(node.state));
  section.querySelector(".summary").textContent =
    (node.details.label ? `${node.details.label}${node.details.location ? `, ${node.details.location}` : ""} · ` : "") +
    `${node.health.online ? "online" : node.health.never_seen ? "NEVER SEEN" : "OFFLINE"} · ` +
    `last seen ${seenText(node.health)} · ` +
    `DI peak ${fmt(node.latest_di_peak)} / threshold ${fmt(node.latest_threshold)}`;
  const b = node.active_baseline;
  section.querySelector(".baseline").textContent = b
    ? `Baseline in use: measurement ${b.measurement_id}, set by ${b.created_by} on ${when(b.created_at)} (${b.reason})`
    : "No active baseline.";
  const page = await api(`/nodes/${encodeURIComponent(node.node_id)}/detections?limit=${TREND_POINTS}`);
  drawTrend(section.querySelector(".trend"), page.items, node.latest_threshold);
  const latest = node.latest_detection;
  const estimate = section.querySelector(".estimate");
  const img = section.querySelector(".heatmap");
  const notices = [];
  if (latest && latest.peak_di === null) {
    notices.push(`Not assessed: ${latest.abstain_reason || "no valid baseline for the current conditions"}.`);
  }
  if (latest && latest.sensor_faults.length) {
    notices.push("Receivers left out of the map: " +
      latest.sensor_faults.map((f) => `${f.rx_index} at ${f.rx_angle_deg.toFixed(0)}° (${f.kind.replace("_", " ")})`).join(", ") + ".");
  }
  const notice = section.querySelector(".notice");
  notice.textContent = notices.join(" ");
  notice.hidden = notices.length === 0;
  if (!latest || latest.peak_di === null) {
    estimate.hidden = true;
    img.hidden = true;
    section.querySelector(".map-caption").textContent = latest
      ? `No DI map of measurement ${latest.measurement_id} (${when(latest.created_at)}).`
      : node.health.never_seen ? "No DI map: the node has never answered." : "No DI map yet (commissioning).";
    shownMaps.delete(node.node_id);
    return;
  }
  img.hidden = false;
  if (latest.axial_mm !== null && latest.angle_deg !== null) {
    estimate.hidden = false;
    const flagged = node.state === "damage" || node.state === "suspected";
    estimate.textContent = `${flagged ? "Estimated defect" : "Map peak (below threshold)"}: ` +
      `${latest.axial_mm.toFixed(0)} mm from the Tx ring, ${latest.angle_deg.toFixed(0)}° (DI ${fmt(latest.peak_di)})`;
    estimate.classList.toggle("flagged", flagged);
    estimate.dataset.axialMm = latest.axial_mm;
    estimate.dataset.angleDeg = latest.angle_deg;
  } else {
    estimate.hidden = true;
  }
  const flaggedMap = node.state === "damage" || node.state === "suspected";
  section.querySelector(".map-caption").textContent =
    `Gateway DI map of measurement ${latest.measurement_id} (${when(latest.created_at)}); colours against the ` +
    `threshold (grey below it); ✕ marks ${flaggedMap ? "the estimate" : "the map's peak"}.`;
  if (shownMaps.get(node.node_id) !== latest.measurement_id) {
    const blob = await api(`/measurements/${latest.measurement_id}/di-maps/gateway.png`, "blob");
    const old = img.src;
    img.src = URL.createObjectURL(blob);
    img.dataset.measurementId = latest.measurement_id;
    if (old.startsWith("blob:")) URL.revokeObjectURL(old);
    shownMaps.set(node.node_id, latest.measurement_id);
  }
}

async function refresh() {
  clearTimeout(timer);
  const status = document.getElementById("status");
  try {
    // The site summary first (one query, whatever the fleet size), then one page of nodes.
    const sites = await api("/fleet/sites");
    const query = new URLSearchParams({ limit: String(PAGE_SIZE) });
    if (view.site) query.set("site", view.site);
    if (view.state) query.set("state", view.state);
    if (view.cursor) query.set("cursor", view.cursor);
    const page = await api(`/fleet/nodes?${query}`);
    const nodes = page.items;
    document.getElementById("key-form").hidden = true;
    document.getElementById("fleet").hidden = false;
    document.getElementById("forget-key").hidden = false;
    renderSites(sites);
    renderFleet(nodes);
    view.next = page.next_cursor;
    document.getElementById("next-page").hidden = !page.next_cursor;
    document.getElementById("first-page").hidden = view.cursors.length === 0;
    document.getElementById("page-info").textContent =
      `page ${view.cursors.length + 1}: ${nodes.length} node(s)${page.next_cursor ? ", more on the next" : ""}`;
    const total = sites.reduce((sum, s) => sum + s.nodes, 0);
    const flagged = (n) => n.state === "damage" || n.state === "suspected";
    const carded = total <= CARD_ALL_UP_TO ? nodes : nodes.filter(flagged).slice(0, MAX_CARDS);
    const listed = new Set(carded.map((n) => n.node_id));
    for (const stale of document.querySelectorAll(".node-card")) {  // decommissioned or filtered out meanwhile
      if (!listed.has(stale.dataset.node)) { stale.remove(); shownMaps.delete(stale.dataset.node); }
    }
    // One node's failure (a map gone missing, a pruned record) must not blank the others.
    const outcomes = await Promise.allSettled(carded.map(renderNode));
    outcomes.forEach((outcome, i) => {
      if (outcome.status === "rejected") {
        if (outcome.reason instanceof Unauthorized) throw outcome.reason;
        const notice = card(carded[i].node_id).querySelector(".notice");
        notice.textContent = `Could not load this node's details: ${outcome.reason.message}`;
        notice.hidden = false;
      }
    });
    const damaged = sites.reduce((sum, s) => sum + (s.by_state.damage || 0), 0);
    const named = sites.filter((s) => s.site !== null).length;
    status.textContent = `${total} node(s)${named ? ` at ${named} site(s)` : ""}, ${damaged} damaged · ` +
      `updated ${new Date().toLocaleTimeString()}`;
  } catch (error) {
    if (error instanceof Unauthorized) {
      localStorage.removeItem(KEY_STORAGE);
      showKeyForm("That API key was refused (unknown or revoked).");
      return;
    }
    status.textContent = `refresh failed: ${error.message} · retrying`;
  }
  timer = setTimeout(refresh, REFRESH_MS);
}

function start() {
  takeKeyFromFragment();
  document.getElementById("key-form").addEventListener("submit", (event) => {
    event.preventDefault();
    localStorage.setItem(KEY_STORAGE, document.getElementById("key-input").value.trim());
    document.getElementById("key-input").value = "";
    refresh();
  });
  document.getElementById("site-filter").addEventListener("change", (event) => setFilter("site", event.target.value));
  document.getElementById("state-filter").addEventListener("change", (event) => setFilter("state", event.target.value));
  document.getElementById("next-page").addEventListener("click", () => {
    view.cursors.push(view.cursor);
    view.cursor = view.next;
    refresh();
  });
  document.getElementById("first-page").addEventListener("click", () => {
    view.cursor = null;
    view.cursors = [];
    refresh();
  });
  document.getElementById("forget-key").addEventListener("click", () => {
    localStorage.removeItem(KEY_STORAGE);
    showKeyForm("");
  });
  if (apiKey()) refresh(); else showKeyForm("");
}

start();
