// PipeSentry dashboard: a static page over the operator API (no build step, no CDN).
// The API key comes from the form (kept in localStorage) or once from the URL fragment
// (#key=...), which browsers never send to the server, so it stays out of access logs.
"use strict";

const API = document.querySelector('meta[name="pipesentry-api-base"]').content;
const REFRESH_MS = 1000 * Number(document.querySelector('meta[name="pipesentry-refresh-s"]').content || "10");
const KEY_STORAGE = "pipesentry.apiKey";
const TREND_POINTS = 100;
const SVG_NS = "http://www.w3.org/2000/svg";

const shownMaps = new Map(); // node_id -> measurement id whose heatmap is displayed
let timer = null;

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

function fmt(value, digits = 4) { return value === null || value === undefined ? "–" : Number(value).toPrecision(digits); }
function when(iso) { return iso ? new Date(iso).toLocaleString() : "–"; }
function stateBadge(state) { return el("span", { class: "state state-" + state, "data-state": state }, state.replaceAll("_", " ")); }

function showKeyForm(message) {
  clearTimeout(timer);
  document.getElementById("key-form").hidden = false;
  document.getElementById("fleet").hidden = true;
  document.getElementById("forget-key").hidden = true;
  document.getElementById("nodes").replaceChildren();
  shownMaps.clear();
  const error = document.getElementById("key-error");
  error.hidden = !message;
  error.textContent = message || "";
  document.getElementById("status").textContent = "API key needed";
}

function renderFleet(nodes) {
  const rows = nodes.map((n) => el("tr", { "data-node": n.node_id },
    el("td", { title: n.details.location || "" }, n.details.label ? `${n.details.label} (${n.node_id})` : n.node_id),
    el("td", {}, stateBadge(n.state)),
    el("td", n.health.online ? {} : { class: "offline" }, n.health.online ? "yes" : "offline"),
    el("td", {}, when(n.health.last_seen_at)),
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
      svg("svg", { class: "trend", viewBox: "0 0 560 140", role: "img", "aria-label": `DI peak trend of ${nodeId}` }),
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

function drawTrend(target, detections) {
  const points = detections.slice().reverse(); // oldest first
  const width = 560, height = 140, left = 44, right = 8, top = 8, bottom = 18;
  const values = points.flatMap((d) => [d.peak_di, d.threshold]).filter((v) => v !== null && v !== undefined);
  target.replaceChildren();
  if (points.length === 0 || values.length === 0) {
    const text = svg("text", { x: left, y: height / 2, class: "axis" });
    text.textContent = "no monitor measurements yet";
    target.append(text);
    return;
  }
  const lo = Math.min(0, ...values), hi = Math.max(...values) * 1.1 || 1;
  const x = (i) => left + (points.length === 1 ? 0 : (i * (width - left - right)) / (points.length - 1));
  const y = (v) => top + (height - top - bottom) * (1 - (v - lo) / (hi - lo));
  const withPeak = points.map((d, i) => [i, d.peak_di]).filter(([, v]) => v !== null && v !== undefined);
  target.append(svg("polyline", { class: "peak", points: withPeak.map(([i, v]) => `${x(i)},${y(v)}`).join(" ") }));
  const withThreshold = points.map((d, i) => [i, d.threshold]).filter(([, t]) => t !== null && t !== undefined);
  if (withThreshold.length) {
    target.append(svg("polyline", { class: "threshold", fill: "none",
      points: withThreshold.map(([i, t]) => `${x(i)},${y(t)}`).join(" ") }));
  }
  for (const v of [lo, hi]) {
    const label = svg("text", { x: 2, y: y(v) + (v === lo ? 0 : 8), class: "axis" });
    label.textContent = fmt(v, 2);
    target.append(label);
  }
  const caption = svg("text", { x: left, y: height - 4, class: "axis" });
  caption.textContent = `DI peak (blue) vs threshold (red dashed), last ${points.length} measurements`;
  target.append(caption);
}

async function renderNode(node) {
  const section = card(node.node_id);
  section.classList.toggle("damage", node.state === "damage");
  section.querySelector(".badge").replaceChildren(stateBadge(node.state));
  section.querySelector(".summary").textContent =
    (node.details.label ? `${node.details.label}${node.details.location ? `, ${node.details.location}` : ""} · ` : "") +
    `${node.health.online ? "online" : "OFFLINE"} · last seen ${when(node.health.last_seen_at)} · ` +
    `DI peak ${fmt(node.latest_di_peak)} / threshold ${fmt(node.latest_threshold)}`;
  const b = node.active_baseline;
  section.querySelector(".baseline").textContent = b
    ? `Baseline in use: measurement ${b.measurement_id}, set by ${b.created_by} on ${when(b.created_at)} (${b.reason})`
    : "No active baseline.";
  const page = await api(`/nodes/${encodeURIComponent(node.node_id)}/detections?limit=${TREND_POINTS}`);
  drawTrend(section.querySelector(".trend"), page.items);
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
      : "No DI map yet (commissioning).";
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
  section.querySelector(".map-caption").textContent =
    `Gateway DI map of measurement ${latest.measurement_id} (${when(latest.created_at)}); ✕ marks the estimate.`;
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
    const nodes = await api("/nodes");
    document.getElementById("key-form").hidden = true;
    document.getElementById("fleet").hidden = false;
    document.getElementById("forget-key").hidden = false;
    renderFleet(nodes);
    const listed = new Set(nodes.map((n) => n.node_id));
    for (const stale of document.querySelectorAll(".node-card")) {  // decommissioned meanwhile
      if (!listed.has(stale.dataset.node)) { stale.remove(); shownMaps.delete(stale.dataset.node); }
    }
    // One node's failure (a map gone missing, a pruned record) must not blank the others.
    const outcomes = await Promise.allSettled(nodes.map(renderNode));
    outcomes.forEach((outcome, i) => {
      if (outcome.status === "rejected") {
        if (outcome.reason instanceof Unauthorized) throw outcome.reason;
        const notice = card(nodes[i].node_id).querySelector(".notice");
        notice.textContent = `Could not load this node's details: ${outcome.reason.message}`;
        notice.hidden = false;
      }
    });
    const damaged = nodes.filter((n) => n.state === "damage").length;
    status.textContent = `${nodes.length} node(s), ${damaged} damaged · updated ${new Date().toLocaleTimeString()}`;
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
  document.getElementById("forget-key").addEventListener("click", () => {
    localStorage.removeItem(KEY_STORAGE);
    showKeyForm("");
  });
  if (apiKey()) refresh(); else showKeyForm("");
}

start();
