// Tessera monitor: one page, three views (#/jobs, #/jobs/ID, #/workers),
// built on the JSON API under /api (docs/monitor.md). Live data comes from
// the server-sent events of /api/events, read with fetch so the token can
// go in the Authorization header (EventSource cannot send headers). The
// token lives in this tab's sessionStorage only.
"use strict";

// Uncaught errors of the page, kept where a test (or a person in the
// console) can read them: not every browser gives WebDriver its console.
window.__monitorErrors = [];
window.addEventListener("error", (e) => window.__monitorErrors.push(String(e.message)));
window.addEventListener("unhandledrejection", (e) => window.__monitorErrors.push(String(e.reason)));

const TOKEN_KEY = "tessera-client-token";
// Least time between two previews (or thumbnails) asked for one frame; the
// server makes at most one a second per frame whatever the viewers.
const PREVIEW_MS = 1000;
const THUMB_MS = 3000;

const S = {
  token: sessionStorage.getItem(TOKEN_KEY) || "",
  needToken: false,
  snap: null,          // the last {jobs, workers} from the event stream
  stream: null,        // AbortController of the event stream
  view: null,          // what #main shows now: {kind, id}
  job: null,           // the job page's state
};

const $ = (sel, root = document) => root.querySelector(sel);

function esc(s) {
  return String(s).replace(/[&<>"']/g, (c) => ({
    "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;", "'": "&#39;",
  })[c]);
}

function headers(extra = {}) {
  const h = Object.assign({}, extra);
  if (S.token) h["Authorization"] = "Bearer " + S.token;
  return h;
}

class ApiError extends Error {
  constructor(status, message) { super(message); this.status = status; }
}

async function api(path, opts = {}) {
  const r = await fetch(path, Object.assign({}, opts, { headers: headers(opts.headers || {}) }));
  if (r.status === 401) {
    signOut("The coordinator refused the token.");
    throw new ApiError(401, "unauthorised");
  }
  if (!r.ok) {
    let msg = r.statusText;
    try { msg = (await r.json()).error || msg; } catch (_) { /* not JSON */ }
    throw new ApiError(r.status, msg);
  }
  return r;
}
const getJson = async (path) => (await api(path)).json();
const postJson = async (path, body) => (await api(path, {
  method: "POST",
  headers: { "Content-Type": "application/json" },
  body: JSON.stringify(body || {}),
})).json();
async function getBlobUrl(path) {
  const blob = await (await api(path)).blob();
  return URL.createObjectURL(blob);
}
// A preview and what it shows: how many of the frame's units, or "written".
async function getPreview(path) {
  const r = await api(path);
  const shows = r.headers.get("X-Tessera-Units-Done") || "";
  return { url: URL.createObjectURL(await r.blob()), shows };
}

// ---- formatting ----------------------------------------------------------

function fmtRate(v) {
  if (!v) return "–";
  const units = [[1e9, "G"], [1e6, "M"], [1e3, "k"]];
  for (const [k, u] of units) if (v >= k) return (v / k).toFixed(v >= 10 * k ? 1 : 2) + " " + u;
  return v.toFixed(0);
}
function fmtDuration(s) {
  if (s === null || s === undefined) return "–";
  s = Math.round(s);
  if (s < 60) return s + " s";
  if (s < 3600) return Math.floor(s / 60) + " m " + String(s % 60).padStart(2, "0") + " s";
  return Math.floor(s / 3600) + " h " + String(Math.floor(s / 60) % 60).padStart(2, "0") + " m";
}
function fmtTime(ms) {
  if (!ms) return "–";
  const d = new Date(ms);
  const today = new Date().toDateString() === d.toDateString();
  return today ? d.toLocaleTimeString() : d.toLocaleString();
}
function fmtAgo(ms) {
  if (!ms) return "–";
  const s = Math.max(0, (Date.now() - ms) / 1000);
  return s < 10 ? s.toFixed(1) + " s ago" : fmtDuration(s) + " ago";
}
const pct = (p) => (100 * p).toFixed(p >= 1 ? 0 : 1) + "%";
const bar = (p) => `<div class="bar"><span style="width:${(100 * p).toFixed(2)}%"></span></div>`;

// ---- sign-in -------------------------------------------------------------

function signOut(why) {
  S.token = "";
  sessionStorage.removeItem(TOKEN_KEY);
  stopEvents();
  showLogin(why);
}

function showLogin(why) {
  S.view = { kind: "login" };
  $("#nav").hidden = true;
  $("#signout").hidden = true;
  $("#main").innerHTML = `
    <div class="login card">
      <h1>Sign in</h1>
      <p class="muted">This coordinator needs its client token (the one <code>tessera submit</code> uses).</p>
      <form id="login-form">
        <input id="token" type="password" autocomplete="current-password" placeholder="client token" required>
        <button class="primary" type="submit">Open the monitor</button>
        <p id="login-error" class="error">${why ? esc(why) : ""}</p>
      </form>
    </div>`;
  $("#login-form").addEventListener("submit", async (e) => {
    e.preventDefault();
    const t = $("#token").value.trim();
    const r = await fetch("/api/jobs", { headers: { Authorization: "Bearer " + t } });
    if (r.status === 401) {
      $("#login-error").textContent = "That is not this coordinator's client token.";
      return;
    }
    S.token = t;
    sessionStorage.setItem(TOKEN_KEY, t);
    start();
  });
}

// ---- live events ---------------------------------------------------------

function stopEvents() {
  if (S.stream) S.stream.abort();
  S.stream = null;
  setLive(false);
}

function setLive(on) {
  const el = $("#live");
  el.classList.toggle("on", on);
  el.textContent = on ? "live" : "offline";
  el.title = on ? "live updates: on" : "live updates: off (reconnecting)";
}

async function runEvents() {
  stopEvents();
  const ctl = new AbortController();
  S.stream = ctl;
  try {
    const r = await fetch("/api/events", { headers: headers({ Accept: "text/event-stream" }), signal: ctl.signal });
    if (r.status === 401) { signOut("The coordinator refused the token."); return; }
    if (!r.ok || !r.body) throw new Error("event stream: " + r.status);
    setLive(true);
    const reader = r.body.pipeThrough(new TextDecoderStream()).getReader();
    let buf = "";
    for (;;) {
      const { value, done } = await reader.read();
      if (done) break;
      buf += value;
      let end;
      while ((end = buf.indexOf("\n\n")) >= 0) {
        const block = buf.slice(0, end);
        buf = buf.slice(end + 2);
        let event = "message";
        const data = [];
        for (const line of block.split("\n")) {
          if (line.startsWith("event:")) event = line.slice(6).trim();
          else if (line.startsWith("data:")) data.push(line.slice(5).replace(/^ /, ""));
        }
        if (event === "farm" && data.length) onSnapshot(JSON.parse(data.join("\n")));
        else if (event === "delta" && data.length && S.snap) onDelta(JSON.parse(data.join("\n")));
      }
    }
  } catch (e) {
    if (ctl.signal.aborted) return;
  }
  if (S.stream === ctl) {
    setLive(false);
    setTimeout(() => { if (S.stream === ctl) runEvents(); }, 2000);
  }
}

function onSnapshot(snap) {
  S.snap = snap;
  render();
}

// A change since the last event: the jobs that changed, each with only its
// changed frames (a frame's units only grow), the jobs gone, and the
// workers when any changed.
function onDelta(d) {
  const jobs = new Map(S.snap.jobs.map((j) => [j.id, j]));
  for (const j of d.jobs) {
    const old = jobs.get(j.id);
    if (old) {
      const frames = new Map(old.frames.map((f) => [f.frame, f]));
      for (const f of j.frames) frames.set(f.frame, f);
      j.frames = [...frames.values()].sort((a, b) => a.frame - b.frame);
    }
    jobs.set(j.id, j);
  }
  for (const id of d.removed) jobs.delete(id);
  S.snap = {
    jobs: [...jobs.values()].sort((a, b) => a.submitted_unix_ms - b.submitted_unix_ms || (a.id < b.id ? -1 : a.id > b.id ? 1 : 0)),
    workers: d.workers || S.snap.workers,
  };
  render();
}

// ---- routing -------------------------------------------------------------

function route() {
  const h = location.hash || "#/jobs";
  const m = h.match(/^#\/jobs\/([^/]+)$/);
  if (m) return { kind: "job", id: decodeURIComponent(m[1]) };
  if (h.startsWith("#/workers")) return { kind: "workers" };
  return { kind: "jobs" };
}

function render() {
  if (S.needToken && !S.token) return;
  const r = route();
  for (const a of document.querySelectorAll("nav a")) {
    a.classList.toggle("active", a.dataset.nav === (r.kind === "workers" ? "workers" : "jobs"));
  }
  if (!S.snap) {
    if (!S.view || S.view.kind !== "wait") {
      S.view = { kind: "wait" };
      $("#main").innerHTML = `<p class="muted">Connecting…</p>`;
    }
    return;
  }
  if (r.kind === "jobs") renderJobs();
  else if (r.kind === "workers") renderWorkers();
  else renderJob(r.id);
}

// ---- jobs ----------------------------------------------------------------

function renderJobs() {
  const jobs = [...S.snap.jobs].reverse(); // newest first
  S.view = { kind: "jobs" };
  S.job = null;
  const rows = jobs.map((j) => `
    <tr data-job="${esc(j.id)}" data-state="${j.state}">
      <td data-label="Name"><a href="#/jobs/${encodeURIComponent(j.id)}">${esc(j.name)}</a><div class="muted">${esc(j.id)}</div></td>
      <td data-label="State" class="state state-${j.state}">${j.state}</td>
      <td data-label="Priority" class="num">${j.priority}</td>
      <td data-label="Progress" class="progress" data-value="${j.progress}">${bar(j.progress)}<span class="pct">${pct(j.progress)}</span></td>
      <td data-label="Rays/s" class="num">${fmtRate(j.rays_per_second)}</td>
      <td data-label="ETA" class="num">${j.state === "running" || j.state === "queued" ? fmtDuration(j.eta_seconds) : "–"}</td>
      <td data-label="Submitted">${fmtTime(j.submitted_unix_ms)}</td>
      <td data-label="Finished">${fmtTime(j.finished_unix_ms)}</td>
    </tr>`).join("");
  $("#main").innerHTML = `
    <h1>Jobs</h1>
    ${jobs.length ? `<table class="cards" id="jobs">
      <thead><tr><th>Name</th><th>State</th><th class="num">Priority</th><th>Progress</th>
      <th class="num">Rays/s</th><th class="num">ETA</th><th>Submitted</th><th>Finished</th></tr></thead>
      <tbody>${rows}</tbody></table>`
      : `<p class="muted" id="no-jobs">No jobs yet. Submit one with <code>tessera submit scene.toml</code>.</p>`}`;
}

// ---- workers -------------------------------------------------------------

function renderWorkers() {
  S.view = { kind: "workers" };
  S.job = null;
  const ws = S.snap.workers;
  const rows = ws.map((w) => `
    <tr data-worker="${esc(w.id)}" data-worker-name="${esc(w.name)}" data-state="${w.state}" class="${w.state === "gone" ? "gone" : ""}">
      <td data-label="Name">${esc(w.name)}<div class="muted">${esc(w.id)} · ${esc(w.version || "")}</div></td>
      <td data-label="State" class="state state-${w.state}">${w.state}${w.quarantined_until_unix_ms && w.quarantined_until_unix_ms > Date.now() ?
        ` <span class="badge quarantined" title="Its results failed validation again and again: no lease until ${esc(new Date(w.quarantined_until_unix_ms).toLocaleTimeString())}">quarantined</span>` : ""}</td>
      <td data-label="Backend">${esc(w.backend)}</td>
      <td data-label="Adapter">${esc(w.adapter || "–")}</td>
      <td data-label="Threads" class="num">${w.threads}</td>
      <td data-label="Leases" class="leases-cell">${w.leases}<div class="leases">${w.holding.slice(0, 4).map((h) =>
        `${esc(h.job)} frame ${h.frame}: ${h.leases === 1 ? "" : h.leases + " leases, "}${h.pixels} px`).join("<br>")}${w.holding.length > 4 ? "<br>…" : ""}</div></td>
      <td data-label="Speed" class="num">${fmtRate(w.samples_per_second)} samples/s<div class="leases">${fmtRate(w.rays_per_second)} rays/s</div></td>
      <td data-label="Last heartbeat">${w.state === "gone" ? "left " + fmtAgo(w.gone_unix_ms) : fmtAgo(w.last_seen_unix_ms)}</td>
      <td data-label="Units done" class="num">${w.units_done}</td>
      <td data-label="Units failed" class="num">${w.units_failed}</td>
    </tr>`).join("");
  $("#main").innerHTML = `
    <h1>Workers</h1>
    ${ws.length ? `<table class="cards" id="workers">
      <thead><tr><th>Name</th><th>State</th><th>Backend</th><th>Adapter</th><th class="num">Threads</th>
      <th>Leases</th><th class="num">Speed</th><th>Last heartbeat</th><th class="num">Done</th><th class="num">Failed</th></tr></thead>
      <tbody>${rows}</tbody></table>`
      : `<p class="muted" id="no-workers">No workers. Start one with <code>tessera worker --coordinator URL</code>.</p>`}`;
}

// ---- one job -------------------------------------------------------------

// The frame the preview follows unless the user picked one: the first
// frame not yet written that has results, else the first not written, else
// the last.
function liveFrame(job) {
  const open = job.frames.filter((f) => !f.written);
  return (open.find((f) => f.units_done > 0) || open[0] || job.frames[job.frames.length - 1]).frame;
}

function renderJob(id) {
  const job = S.snap.jobs.find((j) => j.id === id);
  if (!S.job || S.job.id !== id) {
    if (!job) {
      S.view = { kind: "job", id };
      $("#main").innerHTML = `<p class="error">No job ${esc(id)}.</p><p><a href="#/jobs">All jobs</a></p>`;
      return;
    }
    buildJob(job);
  }
  if (job) updateJob(job);
}

function buildJob(job) {
  S.view = { kind: "job", id: job.id };
  S.job = {
    id: job.id, picked: null, frame: null,
    preview: { busy: false, at: 0, key: "", url: null, version: 0 },
    thumbs: new Map(), // frame -> {key, at, url}
    failuresKey: "", armed: null,
  };
  const aspect = `${job.settings.width} / ${job.settings.height}`;
  $("#main").innerHTML = `
    <p><a href="#/jobs">← All jobs</a></p>
    <div class="job-head">
      <div>
        <h1 id="job-name">${esc(job.name)}</h1>
        <div><span id="job-state" class="state"></span> · <span class="muted">${esc(job.id)}</span></div>
      </div>
      <div class="controls">
        <label for="priority">Priority</label>
        <input id="priority" type="number" step="1" value="${job.priority}">
        <button id="set-priority">Set</button>
        <button id="cancel" class="danger">Cancel job</button>
      </div>
    </div>
    <p id="job-error" class="error"></p>
    <div class="card" style="margin-top:0.6rem">
      <div id="job-progress"></div>
      <div class="legend" id="job-stats"></div>
    </div>
    <div class="grid" style="margin-top:1rem">
      <section>
        <h2>Frame <span id="preview-frame"></span> <span class="muted" id="preview-note"></span></h2>
        <div class="preview-wrap" id="preview-wrap">
          <img id="preview" alt="preview of the frame" data-version="0">
          <div class="overlay" id="overlay"></div>
        </div>
        <div class="legend"><span><i class="leased"></i>leased</span><span><i class="partial"></i>some samples in</span><span><i class="pending"></i>waiting</span></div>
        <div class="controls" id="frame-actions" hidden>
          <button id="full-size">View full size</button>
          <button id="download">Download PNG</button>
        </div>
      </section>
      <section>
        <h2>Settings</h2>
        <dl class="settings" id="settings"></dl>
      </section>
    </div>
    <h2>Frames</h2>
    <div class="frames" id="frames" style="--aspect:${aspect}"></div>
    <h2>Failures</h2>
    <div id="failures"><p class="muted">None.</p></div>`;

  $("#set-priority").addEventListener("click", async () => {
    const v = Number($("#priority").value);
    if (!Number.isInteger(v)) { jobError("The priority is a whole number."); return; }
    try {
      await postJson(`/api/jobs/${encodeURIComponent(job.id)}/priority`, { priority: v });
      jobError("");
      const field = $("#priority");
      if (field) field.dataset.dirty = "";
    } catch (e) { jobError(e.message); }
  });
  $("#priority").addEventListener("input", () => { $("#priority").dataset.dirty = "1"; });
  // Two clicks to cancel (no dialog: works the same on a phone).
  $("#cancel").addEventListener("click", async () => {
    const b = $("#cancel");
    if (!b.classList.contains("armed")) {
      b.classList.add("armed");
      b.textContent = "Click again to cancel";
      clearTimeout(S.job.armed);
      S.job.armed = setTimeout(() => { b.classList.remove("armed"); b.textContent = "Cancel job"; }, 4000);
      return;
    }
    b.classList.remove("armed");
    b.textContent = "Cancel job";
    try {
      await postJson(`/api/jobs/${encodeURIComponent(job.id)}/cancel`);
      jobError("");
    } catch (e) { jobError(e.message); }
  });
  $("#full-size").addEventListener("click", () => openViewer(job.id, S.job.frame));
  $("#download").addEventListener("click", () => download(job.id, S.job.frame));
}

function updateJob(job) {
  const st = S.job;
  const stEl = $("#job-state");
  stEl.textContent = job.state;
  stEl.className = `state state-${job.state}`;
  stEl.dataset.state = job.state;
  const ended = ["done", "failed", "cancelled"].includes(job.state);
  $("#cancel").disabled = ended;
  $("#set-priority").disabled = ended;
  $("#priority").disabled = ended;
  if (!$("#priority").dataset.dirty && document.activeElement !== $("#priority")) $("#priority").value = job.priority;
  jobError(job.error || "");
  const p = $("#job-progress");
  p.dataset.value = job.progress;
  p.innerHTML = `${bar(job.progress)}<span class="pct" id="job-pct">${pct(job.progress)}</span>
    <span class="pct"> · ${job.units_done} / ${job.units_total} units</span>`;
  $("#job-stats").innerHTML = `
    <span>Rays/s <b>${fmtRate(job.rays_per_second)}</b></span>
    <span>ETA <b>${ended ? "–" : fmtDuration(job.eta_seconds)}</b></span>
    <span>Submitted <b>${fmtTime(job.submitted_unix_ms)}</b></span>
    <span>Finished <b>${fmtTime(job.finished_unix_ms)}</b></span>
    <span>Results late/duplicate/rejected <b>${job.results_late}/${job.results_duplicate}/${job.results_rejected}</b></span>
    ${job.requirements && job.requirements.length ? `<span>Requires <b>${esc(job.requirements.join(", "))}</b></span>` : ""}
    ${job.unrunnable ? `<span id="job-unrunnable">Waiting <b>${esc(job.unrunnable)}</b></span>` : ""}
    ${job.waiting_for && job.waiting_for.length ? `<span id="job-waiting-for">Waiting for <b>${esc(job.waiting_for.join(", "))}</b></span>` : ""}
    ${job.failure_classes && Object.keys(job.failure_classes).length ? `<span id="job-failure-classes">Failures <b>${Object.entries(job.failure_classes)
      .map(([k, n]) => `${esc(k)} ${n}`).join(", ")}</b> (blocklist after ${job.blocklist_after})</span>` : ""}
    ${job.blocklisted && job.blocklisted.length ? `<span id="job-blocklist">Blocklisted <b>${job.blocklisted
      .map((b) => `${esc(b.name)} (${b.failures} failed, until ${esc(fmtTime(b.until_unix_ms))})`).join(", ")}</b></span>` : ""}
    ${job.adaptive && job.adaptive.mode === "image" ? `<span>Blocks settled <b id="job-converged">${pct(job.adaptive.converged_share)}</b></span>
    <span>Estimated image RMSE <b id="job-estimated-error">${job.adaptive.estimated_error.toExponential(2)}</b></span>`
    : job.adaptive ? `<span>Blocks converged <b id="job-converged">${pct(job.adaptive.converged_share)}</b></span>
    <span>Estimated error <b id="job-estimated-error">${job.adaptive.estimated_error.toExponential(2)}</b></span>` : ""}`;
  const s = job.settings;
  const a = job.adaptive;
  // An adaptive job's samples are its bounds and its target decides.
  const samples = a ? [["Samples", `${a.min_samples}–${a.max_samples} (adaptive)`],
    ...(a.target_error > 0 ? [["Target error", a.target_error]] : []),
    ...(a.relative_error > 0 ? [["Relative error", a.relative_error]] : [])]
    : [["Samples", s.samples]];
  $("#settings").innerHTML = [
    ["Scene", s.scene], ["Size", `${s.width} × ${s.height}`], ...samples,
    ["Integrator", s.integrator], ["Max depth", s.max_depth], ["Sampler", s.sampler],
    ["Frames", s.first_frame === s.last_frame ? s.first_frame : `${s.first_frame}–${s.last_frame}`],
    ["Tile size", s.tile_size], ["Samples a unit", s.samples_per_unit], ["Attempts a unit", s.max_attempts],
  ].map(([k, v]) => `<dt>${esc(k)}</dt><dd>${esc(v)}</dd>`).join("");

  st.frame = st.picked !== null ? st.picked : liveFrame(job);
  const f = job.frames.find((x) => x.frame === st.frame);
  $("#preview-frame").textContent = st.frame;
  $("#preview-note").textContent = f.written ? "(done)" : `(${f.units_done} / ${f.units_total} units)`;
  $("#frame-actions").hidden = !f.written;
  refreshPreview(job, f);
  refreshFrames(job);
  refreshFailures(job);
}

// The job page's error line; a no-op once the page has moved on (an answer
// can arrive after the user left the job's page).
function jobError(msg) {
  const el = $("#job-error");
  if (el) el.textContent = msg;
}

async function refreshPreview(job, f) {
  const p = S.job.preview;
  const key = `${job.id}/${f.frame}/${f.units_done}/${f.written}`;
  if (p.busy || key === p.key) return;
  const wait = PREVIEW_MS - (Date.now() - p.at);
  if (wait > 0) {
    // Ask again when the throttle allows, unless a newer snapshot does.
    clearTimeout(p.timer);
    p.timer = setTimeout(() => { if (S.job && S.job.preview === p) refreshPreview(job, f); }, wait);
    return;
  }
  p.busy = true;
  p.at = Date.now();
  try {
    const base = `/api/jobs/${encodeURIComponent(job.id)}/frames/${f.frame}`;
    const [{ url, shows }, detail] = await Promise.all([
      getPreview(`${base}/preview.png`),
      f.written ? null : getJson(base),
    ]);
    if (!S.job || S.job.preview !== p) { URL.revokeObjectURL(url); return; }
    const img = $("#preview");
    await new Promise((ok) => { img.onload = ok; img.onerror = ok; img.src = url; });
    // The page may have moved on while the image loaded.
    if (!S.job || S.job.preview !== p) { URL.revokeObjectURL(url); return; }
    if (p.url) URL.revokeObjectURL(p.url);
    p.url = url;
    // What the image holds, which may be a moment older than the snapshot
    // (the server makes a frame's preview at most once a second): asked
    // again until it catches up.
    const written = shows === "written";
    const units = written ? f.units_total : Number(shows);
    p.key = `${job.id}/${f.frame}/${units}/${written}`;
    p.version += 1;
    img.dataset.version = p.version;
    img.dataset.frame = f.frame;
    img.dataset.unitsDone = units;
    img.dataset.written = written ? "1" : "";
    img.classList.toggle("smooth", img.naturalWidth >= job.settings.width);
    drawTiles(detail, job);
  } catch (e) {
    // A 503 is a frame being written.
    if (e.status !== 503) jobError("preview: " + e.message);
  } finally {
    p.busy = false;
  }
}

function drawTiles(detail, job) {
  const o = $("#overlay");
  if (!detail) { o.innerHTML = ""; return; }
  const W = detail.width, H = detail.height;
  o.innerHTML = detail.tiles.filter((t) => t.state !== "done").map((t) =>
    `<div class="tile ${t.state}" style="left:${100 * t.x / W}%;top:${100 * t.y / H}%;width:${100 * t.width / W}%;height:${100 * t.height / H}%"></div>`
  ).join("");
}

function refreshFrames(job) {
  const box = $("#frames");
  const st = S.job;
  for (const f of job.frames) {
    let el = box.querySelector(`[data-frame="${f.frame}"]`);
    if (!el) {
      el = document.createElement("div");
      el.className = "thumb";
      el.dataset.frame = f.frame;
      el.innerHTML = `<img alt="frame ${f.frame}"><div class="cap"></div>`;
      el.addEventListener("click", () => {
        st.picked = st.picked === f.frame ? null : f.frame;
        st.preview.key = "";
        st.preview.at = 0;
        render();
      });
      box.appendChild(el);
    }
    el.classList.toggle("selected", f.frame === st.frame);
    $(".cap", el).textContent = `${f.frame} · ${f.written ? "done" : pct(f.progress)}`;
    const t = st.thumbs.get(f.frame) || { key: "", at: 0, busy: false };
    st.thumbs.set(f.frame, t);
    const key = `${f.units_done}/${f.written}`;
    // A frame with nothing merged has nothing to show; others refresh slowly.
    if (t.busy || key === t.key || f.units_done === 0 || (!f.written && Date.now() - t.at < THUMB_MS)) continue;
    t.busy = true;
    t.at = Date.now();
    getBlobUrl(`/api/jobs/${encodeURIComponent(job.id)}/frames/${f.frame}/preview.png?max=160`)
      .then((url) => {
        const img = $("img", el);
        if (img.src) URL.revokeObjectURL(img.src);
        img.src = url;
        // What it shows, for scripts and tests (as the preview's dataset).
        img.dataset.unitsDone = f.units_done;
        img.dataset.written = f.written ? "1" : "";
        t.key = key;
      })
      .catch(() => {})
      .finally(() => { t.busy = false; });
  }
}

async function refreshFailures(job) {
  const st = S.job;
  // Failures change only with the counts the snapshot carries.
  const key = `${job.units_done}/${job.state}/${job.results_rejected}/${job.error}`;
  if (st.failuresKey === key || st.failuresBusy) return;
  st.failuresBusy = true;
  try {
    // The failures only: one frame of the job is enough.
    const d = await getJson(`/api/jobs/${encodeURIComponent(job.id)}?frames_max=1`);
    st.failuresKey = key;
    $("#failures").innerHTML = d.failures.length ? `<ul class="failures">${d.failures.map((f) =>
      `<li>Unit ${f.unit}: frame ${f.frame}, tile ${f.rect.width}×${f.rect.height}+${f.rect.x}+${f.rect.y}, samples ${f.samples[0]}–${f.samples[1]}
       <ul>${f.messages.map((m) => `<li><code>${esc(m)}</code></li>`).join("")}</ul></li>`).join("")}</ul>`
      : `<p class="muted">None.</p>`;
  } catch (_) { /* shown by the next snapshot */ }
  finally { st.failuresBusy = false; }
}

async function openViewer(jobId, frame) {
  const v = $("#viewer");
  $("#viewer-title").textContent = `${jobId} · frame ${frame}`;
  const img = $("#viewer-img");
  if (img.src) URL.revokeObjectURL(img.src);
  img.src = await getBlobUrl(`/api/jobs/${encodeURIComponent(jobId)}/frames/${frame}/image.png`);
  v.hidden = false;
}

async function download(jobId, frame) {
  const url = await getBlobUrl(`/api/jobs/${encodeURIComponent(jobId)}/frames/${frame}/image.png?download=1`);
  const a = document.createElement("a");
  a.href = url;
  a.download = `${jobId}_frame_${String(frame).padStart(4, "0")}.png`;
  document.body.appendChild(a);
  a.click();
  a.remove();
  setTimeout(() => URL.revokeObjectURL(url), 10000);
}

// ---- start ---------------------------------------------------------------

async function start() {
  $("#nav").hidden = false;
  $("#signout").hidden = !S.needToken;
  S.snap = null;
  S.view = null;
  S.job = null;
  render();
  runEvents();
}

window.addEventListener("hashchange", () => { S.job = null; render(); });
document.addEventListener("DOMContentLoaded", async () => {
  $("#signout").addEventListener("click", () => signOut(""));
  $("#viewer-close").addEventListener("click", () => { $("#viewer").hidden = true; });
  document.addEventListener("keydown", (e) => { if (e.key === "Escape") $("#viewer").hidden = true; });
  // Relative times ("3.2 s ago") move between snapshots too.
  setInterval(() => { if (S.view && S.view.kind === "workers" && S.snap) renderWorkers(); }, 1000);
  try {
    const info = await (await fetch("/api/info")).json();
    S.needToken = info.token_required;
  } catch (_) {
    $("#main").innerHTML = `<p class="error">Cannot reach the coordinator.</p>`;
    return;
  }
  if (S.needToken && !S.token) showLogin("");
  else start();
});
