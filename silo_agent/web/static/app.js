// The operator's page: read-only. State arrives as server-sent events (api/events); pictures
// are drawn by the agent (matplotlib) and only fetched here when the scan they show changes.
"use strict";
const $ = (id) => document.getElementById(id);
let shownScan = null;
let span = "week";
let liveCount = 0;

function fixed(value, digits) {
  return value === null || value === undefined ? "–" : Number(value).toFixed(digits);
}

function text(id, value) { $(id).textContent = value; }

function cell(row, value, cls) {
  const td = row.insertCell();
  td.textContent = value === null || value === undefined ? "–" : String(value);
  if (cls) td.className = cls;
  return td;
}

function link(row, href, label) {
  const a = document.createElement("a");
  a.href = href; a.textContent = label;
  return a;
}

async function getJSON(url) {
  const response = await fetch(url, { credentials: "same-origin" });
  if (!response.ok) throw new Error(`${url}: ${response.status}`);
  return response.json();
}

function showLatest(latest) {
  $("no-scan").hidden = latest !== null;
  $("figures").hidden = latest === null;
  if (latest === null) return;
  const p = latest.published;
  const d = latest.details;
  const volume = $("volume");
  volume.textContent = fixed(p.volume_m3, 3);
  volume.dataset.published = JSON.stringify(p.volume_m3);
  volume.title = `published on P/volume: ${p.volume_m3} m³`;
  const mass = $("mass");
  mass.textContent = fixed(p.mass_t, 3);
  mass.dataset.published = JSON.stringify(p.mass_t);
  const level = p.level || {};
  text("level", `${fixed(level.min, 3)} / ${fixed(level.mean, 3)} / ${fixed(level.max, 3)}`);
  $("coverage").textContent = fixed(p.coverage * 100, 1);
  $("coverage").dataset.published = JSON.stringify(p.coverage);
  const valid = $("valid");
  valid.textContent = (p.valid ? "valid" : `invalid: ${d.invalid_reason || "?"}`) + (p.degraded ? " · degraded" : "");
  valid.className = p.valid && !p.degraded ? "good" : "bad";
  valid.dataset.valid = String(p.valid);
  valid.dataset.degraded = String(p.degraded);
  text("captured-at", p.captured_at);
  text("scan-id", p.scan_id);
  $("report-link").href = `scans/${encodeURIComponent(p.scan_id)}/report.html`;
  $("export-link").href = `scans/${encodeURIComponent(p.scan_id)}/export.tar.gz`;
  for (const [key, id, show] of [["fill_ratio", "fill", (v) => `${fixed(v * 100, 1)} %`],
                                  ["headspace_m", "headspace", (v) => fixed(v, 3)],
                                  ["capacity_m3", "capacity", (v) => fixed(v, 3)]]) {
    const value = d[key];  // null without a bin: the row hidden (not "fill 0.0 %")
    const shown = value !== null && value !== undefined;
    $(`${id}-row`).hidden = !shown;
    if (shown) text(id, show(value));
  }
  const residuals = $("residuals").tBodies[0];
  residuals.replaceChildren();
  for (const [pair, metres] of Object.entries(d.registration_residual_m || {})) {
    const row = residuals.insertRow();
    cell(row, pair);
    cell(row, metres === null ? null : `${fixed(metres * 1000, 1)} mm`);
  }
}

let cameraScan = {};
function showCameras(state) {
  const body = $("cameras").tBodies[0];
  body.replaceChildren();
  const latest = state.latest;
  const used = latest ? (latest.details.cameras || {}).used || [] : [];
  for (const camera of state.cameras || []) {
    const row = body.insertRow();
    const seen = cameraScan[camera.serial] || {};
    cell(row, camera.serial);
    cell(row, camera.state, camera.state === "ok" ? "good" : camera.state === "failed" ? "bad" : "");
    cell(row, used.includes(camera.serial) ? latest.published.captured_at : null);
    cell(row, seen.points);
    cell(row, seen.coverage === undefined ? null : `${fixed(seen.coverage * 100, 1)} %`);
    cell(row, seen.gravity_deg === undefined || seen.gravity_deg === null ? null : `${fixed(seen.gravity_deg, 2)}°`);
    cell(row, camera.error);
  }
}

function showAlarms(state) {
  const body = $("alarms").tBodies[0];
  body.replaceChildren();
  for (const alarm of Object.values(state.alarms || {})) {
    const row = body.insertRow();
    cell(row, alarm.type);
    cell(row, alarm.state, alarm.state === "raised" ? "raised" : "");
    cell(row, alarm.severity);
    cell(row, alarm.scan_id);
    cell(row, alarm.message);
  }
  const events = $("events");
  events.replaceChildren();
  for (const event of (state.events || []).slice().reverse()) {
    const li = document.createElement("li");
    li.textContent = `${event.ts} ${event.type} ${event.state} (${event.severity}): ${event.message}`;
    if (event.state === "raised") li.className = "raised";
    events.appendChild(li);
  }
  if (!events.children.length) events.innerHTML = "<li>none since the agent started</li>";
}

async function showMap(scanId) {
  const layout = await getJSON(`api/map/${encodeURIComponent(scanId)}.json`);
  const img = $("map");
  img.dataset.scanId = scanId;
  img.src = `api/map/${encodeURIComponent(scanId)}.png`;
  text("map-scan", scanId);
  // heights above the floor: vmin is the floor's silo-frame z (pictures.MapLayout.scale_m)
  text("legend-min", `${fixed(0, 2)} m`);
  text("legend-max", `${fixed(layout.vmax - layout.vmin, 2)} m`);
  $("legend-bar").style.background = `linear-gradient(to right, ${layout.legend.join(", ")})`;
  cameraScan = Object.fromEntries((layout.cameras || []).map((c) => [c.serial, c]));
}

async function showHistory() {
  const wanted = span;
  const response = await fetch(`api/history.svg?range=${wanted}`, { credentials: "same-origin" });
  if (!response.ok) return;
  const svg = await response.text();
  const answers = $("history").dataset;  // counted, drawn or dropped: a reader can wait on it
  answers.answered = String(Number(answers.answered || 0) + 1);
  // a range clicked since has its own request: an answer overtaken by it is dropped (a slow
  // "day" had drawn over "all" while the "all" button stayed marked)
  if (wanted !== span) return;
  const history = $("history");
  history.innerHTML = svg;
  history.dataset.range = wanted;
  for (const button of document.querySelectorAll("[data-range]")) {
    button.classList.toggle("on", button.dataset.range === span);
  }
}

// The scan list, a page at a time (api/scans): the newest page first, older pages appended by
// the "older scans" button; a new scan goes on top, the pages shown below it stay.
const SCAN_PAGE = 50;
let scanList = [];  // the scans listed, newest first
let olderScans = false;  // the archive holds scans older than the last listed

function scanPage(before) {
  const cursor = before ? `&before=${encodeURIComponent(before)}` : "";
  return fetch(`api/scans?limit=${SCAN_PAGE}${cursor}`, { credentials: "same-origin" });
}

async function pageOf(before) {
  const response = await scanPage(before);
  if (!response.ok) throw new Error(`api/scans: ${response.status}`);
  return response.json();
}

function drawScans() {
  const body = $("scans").tBodies[0];
  body.replaceChildren();
  for (const scan of scanList) {
    const row = body.insertRow();
    row.dataset.scanId = scan.scan_id;
    cell(row, scan.scan_id);
    cell(row, scan.captured_at);
    cell(row, fixed(scan.volume_m3, 3));
    cell(row, fixed(scan.mass_t, 3));
    const result = !scan.has_result ? "no result" : scan.valid ? "valid" : "invalid";
    const degraded = scan.has_result && scan.degraded;  // a camera failed: marked as in Latest scan
    cell(row, result + (degraded ? " · degraded" : ""), scan.valid && !degraded ? "good" : "bad");
    const links = row.insertCell();
    if (scan.has_result) {
      links.appendChild(link(row, `scans/${encodeURIComponent(scan.scan_id)}/report.html`, "report"));
      links.append(" · ");
    }
    links.appendChild(link(row, `scans/${encodeURIComponent(scan.scan_id)}/export.tar.gz`, "export"));
  }
  $("older-scans").hidden = !olderScans;
}

// the newest page over the list shown: its scans replace theirs (a result kept since), newer
// ones go on top and the older pages shown stay; when more than a page arrived since, pages
// are read down to the scans shown
async function showScans() {
  let { scans: fetched, more } = await pageOf(null);
  const shown = new Set(scanList.map((s) => s.scan_id));
  const newestShown = scanList.length ? scanList[0].captured_at : null;
  while (more && newestShown !== null && !fetched.some((s) => shown.has(s.scan_id)) &&
         fetched[fetched.length - 1].captured_at >= newestShown) {
    const older = await pageOf(fetched[fetched.length - 1].scan_id);
    fetched = fetched.concat(older.scans);
    more = older.more;
  }
  const oldest = fetched.length ? fetched[fetched.length - 1].scan_id : null;
  const below = scanList.findIndex((s) => s.scan_id === oldest);
  if (more && below >= 0) {
    scanList = fetched.concat(scanList.slice(below + 1));
  } else {  // the first list, the whole archive read, or no scan shown is left
    scanList = fetched;
    olderScans = more;
  }
  drawScans();
}

async function showOlderScans() {
  const button = $("older-scans");
  button.disabled = true;  // one page at a time: a second click waits for the first
  try {
    const response = await scanPage(scanList[scanList.length - 1].scan_id);
    if (response.status === 400) {  // the last scan listed was removed (retention): start again
      scanList = [];
      await showScans();
    } else if (response.ok) {
      const page = await response.json();
      const shown = new Set(scanList.map((s) => s.scan_id));
      scanList = scanList.concat(page.scans.filter((s) => !shown.has(s.scan_id)));
      olderScans = page.more;
      drawScans();
    }
  } finally {
    button.disabled = false;
  }
}
$("older-scans").addEventListener("click", showOlderScans);

// the last scan, when it gave no result: it is in no list, so it is named above the figures
// of the last scan that did
function showFailure(failure) {
  const line = $("last-failure");
  line.hidden = !failure;
  line.dataset.scanId = failure ? failure.scan_id : "";
  if (failure) {
    line.textContent = `Last scan ${failure.scan_id} (${failure.captured_at}) gave no result: ` +
      `${failure.reason || "?"}. The figures below are from the scan before it.`;
  }
}

async function apply(state) {
  text("silo-id", state.silo_id);
  showFailure(state.last_failure);
  showLatest(state.latest);
  showAlarms(state);
  showCameras(state);  // with the figures, not after the pictures: both of one scan
  showLive(state.live || {});
  const scanId = state.latest ? state.latest.published.scan_id : null;
  $("map").hidden = scanId === null;  // no broken picture before the first scan
  if (scanId !== shownScan) {
    try {  // marked shown once drawn: a fetch that fails (the agent restarting) is retried
      if (scanId !== null) await showMap(scanId);
      await Promise.all([showHistory(), showScans()]);
      shownScan = scanId;
      showCameras(state);  // again, with the new map's points and coverage per camera
    } catch (error) {
      console.warn("scan not drawn yet, retried with the next state", error);
    }
  }
  document.body.dataset.scanId = scanId || "";
}

function showLive(live) {
  const fresh = live.time && Date.now() - Date.parse(live.time) < 10000;
  $("live-section").hidden = !live.count;
  $("live-badge").hidden = !fresh;
  if (live.count && live.count !== liveCount) {
    liveCount = live.count;
    $("live-map").src = `api/live.png?n=${live.count}`;
    text("live-info", `${live.session_id || ""} · map ${live.sequence ?? ""} · ${live.time || ""}`);
  }
}

for (const button of document.querySelectorAll("[data-range]")) {
  button.addEventListener("click", () => { span = button.dataset.range; showHistory(); });
}

function connected(ok) {
  const badge = $("connection");
  badge.textContent = ok ? "connected" : "reconnecting…";
  badge.classList.toggle("ok", ok);
  // with the agent away the figures are as it last said them: shown faded, not as current
  document.body.classList.toggle("stale", !ok);
}

// the first state at once, not after the event stream's first message; apply() draws each
// scan's map once, whichever of the two arrives first (the stream reports the connection)
getJSON("api/state").then(apply).catch(() => {});
const events = new EventSource("api/events");
events.addEventListener("state", (e) => { connected(true); apply(JSON.parse(e.data)); });
events.onerror = () => connected(false);
