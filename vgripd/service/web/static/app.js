// The vgripd operator page: plain DOM, no framework, no build step.
// Data: /api/jobs, /api/registers, /api/config; live: /api/events (SSE: the status, each job),
// /api/status on loading and while the stream fails.
"use strict";

const $ = (id) => document.getElementById(id);
const fmt = (x, d = 1) => (typeof x === "number" ? x.toFixed(d) : x == null ? "" : String(x));
let jobs = [];
let lastStatus = null;

function rows(tbody, pairs) {
  tbody.replaceChildren(...pairs.map(([k, v]) => {
    const tr = document.createElement("tr");
    for (const cell of [k, v]) {
      const td = document.createElement("td");
      td.textContent = cell;
      tr.append(td);
    }
    return tr;
  }));
}

function cells(values) {
  const tr = document.createElement("tr");
  for (const v of values) {
    const td = document.createElement("td");
    if (v instanceof Node) td.append(v); else td.textContent = v;
    tr.append(td);
  }
  return tr;
}

async function getJSON(url) {
  const resp = await fetch(url, { cache: "no-store" });
  if (!resp.ok) throw new Error(`${url}: ${resp.status}`);
  return resp.json();
}

function imageURL(job, side) {
  return `/api/jobs/${job.id}/image/${side}.jpg?t=${Math.round(job.t_wall * 1000)}`;
}

// [url side, caption] of each image of a job: left (and right), or every camera of a
// multi-camera cell (view0, view1, ... captioned with the camera's name).
function jobViews(job) {
  if (!job.images) return [];
  if (job.views && job.views.length) return job.views;
  return job.stereo ? [["left", "left"], ["right", "right"]] : [["left", "left"]];
}

// One figure per image of the job (rebuilt only when the set of cameras changes).
function showImages(job) {
  const box = document.querySelector("#live .images");
  const views = jobViews(job);
  const want = views.map(([side, caption]) => `${side}=${caption}`).join(",");
  if (box.dataset.views !== want) {
    box.replaceChildren(...views.map(([side, caption]) => {
      const fig = document.createElement("figure");
      const img = document.createElement("img");
      img.id = `img-${side}`;
      img.alt = `${caption} image of the last job`;
      const cap = document.createElement("figcaption");
      cap.textContent = caption;
      fig.append(img, cap);
      return fig;
    }));
    box.dataset.views = want;
    box.classList.toggle("many", views.length > 2);
  }
  for (const [side] of views) $(`img-${side}`).src = imageURL(job, side);
}

function showJob(job) {
  $("job-title").textContent = `${job.id} (seq ${job.seq} from ${job.link}, recipe ${job.recipe}, ` +
    `${new Date(job.t_wall * 1000).toLocaleTimeString()})`;
  const st = $("job-status");
  const told = job.published === job.status ? "" :
    job.published == null ? ", NOT DELIVERED" : `, published as ${job.published}`;
  st.textContent = `job ${job.id}: ${job.status} (${job.status_code})` +
    `${job.message ? ": " + job.message : ""}${told}, cycle ${fmt(job.cycle_ms)} ms`;
  st.className = "status " + (job.status.startsWith("OK") ? "ok" : "bad");
  showImages(job);
  const t = job.target;
  rows($("job-target").tBodies[0], t ? t.fields.map((f, i) => [f, fmt(t.values[i], 3)])
    .concat([["vendor", t.vendor]]) : [["", "no pose sent"]]);
  rows($("job-residuals").tBodies[0], Object.entries(job.residuals).map(([k, v]) => [k, fmt(v, 3)]));
  rows($("job-timings").tBodies[0], Object.entries(job.timings_ms).map(([k, v]) => [k, fmt(v, 1)]));
  const missing = job.features_missing.length ? `; missing: ${job.features_missing.join(", ")}` : "";
  $("job-features").textContent = job.features_used.length || missing ?
    `features used: ${job.features_used.join(", ") || "none"}${missing}` : "";
}

function showHistory() {
  const tbody = $("jobs").tBodies[0];
  tbody.replaceChildren(...jobs.map((j) => {
    let links = "";
    if (j.images) {
      const span = document.createElement("span");
      for (const [side, caption] of jobViews(j)) {
        const a = document.createElement("a");
        a.href = imageURL(j, side);
        a.target = "_blank";
        a.textContent = caption + " ";
        span.append(a);
      }
      links = span;
    }
    const res = Object.entries(j.residuals).map(([k, v]) => `${k} ${fmt(v, 2)}`).join(", ");
    return cells([j.id, new Date(j.t_wall * 1000).toLocaleTimeString(), j.link, j.recipe, j.status,
      fmt(j.cycle_ms), res, links]);
  }));
  drawTrend();
}

// Inline SVG: cycle time (left axis) and epipolar residual (right axis), oldest on the left.
function drawTrend() {
  const svg = $("trend");
  const W = 800, H = 200, L = 50, R = 50, T = 10, B = 20;
  const pts = jobs.slice().reverse();
  const ns = "http://www.w3.org/2000/svg";
  const node = (name, attrs, text) => {
    const n = document.createElementNS(ns, name);
    for (const [k, v] of Object.entries(attrs)) n.setAttribute(k, v);
    if (text != null) n.textContent = text;
    return n;
  };
  const parts = [node("rect", { x: L, y: T, width: W - L - R, height: H - T - B, fill: "none", stroke: "#ccc" })];
  if (pts.length) {
    const cyc = pts.map((j) => j.cycle_ms);
    const epi = pts.map((j) => j.residuals.epipolar_px ?? null);
    const cmax = Math.max(...cyc) * 1.1 || 1;
    const evals = epi.filter((v) => v != null);
    const emax = Math.max(lastStatus?.recalibrate?.threshold_px ?? 0, ...evals) * 1.1 || 1;
    const x = (i) => L + (pts.length === 1 ? 0.5 : i / (pts.length - 1)) * (W - L - R);
    const y = (v, max) => H - B - (v / max) * (H - T - B);
    const line = (vals, max, colour) => {
      const d = vals.map((v, i) => (v == null ? null : `${x(i).toFixed(1)},${y(v, max).toFixed(1)}`))
        .filter((p) => p).join(" ");
      if (d) parts.push(node("polyline", { points: d, fill: "none", stroke: colour, "stroke-width": 1.5 }));
    };
    line(cyc, cmax, "#1f6fd0");
    line(epi, emax, "#d07a1f");
    const thr = lastStatus?.recalibrate?.threshold_px;
    if (thr && evals.length) {
      parts.push(node("line", { x1: L, x2: W - R, y1: y(thr, emax), y2: y(thr, emax), stroke: "#d07a1f", "stroke-dasharray": "4 3" }));
    }
    parts.push(node("text", { x: 4, y: T + 10, "font-size": 11, fill: "#1f6fd0" }, `${fmt(cmax, 0)} ms`));
    parts.push(node("text", { x: 4, y: H - B, "font-size": 11, fill: "#1f6fd0" }, "0"));
    parts.push(node("text", { x: W - R + 4, y: T + 10, "font-size": 11, fill: "#d07a1f" }, `${fmt(emax, 2)} px`));
    parts.push(node("text", { x: L, y: H - 4, "font-size": 11 }, `job ${pts[0].id}`));
    parts.push(node("text", { x: W - R - 60, y: H - 4, "font-size": 11 }, `job ${pts[pts.length - 1].id}`));
  }
  svg.replaceChildren(...parts);
}

// The header names the active recipe among a few ("recipe 2 plate-b (of 0 default, 1 plate-a,
// 2 plate-b)") and counts many ("recipe 2 plate-b (of 40 recipes; 1 NOT CALIBRATED)"), so any
// number fits; the full list is under "Calibration and config" (and the header's tooltip).
const HEADER_RECIPES = 4;
function recipeText(r) {
  if (!r) return "";
  const active = r.active === null ? "recipe: none yet" : `recipe ${r.active} ${r.active_name}`;
  if (r.recipes.length <= 1) return active;  // one recipe: nothing to choose among
  if (r.recipes.length <= HEADER_RECIPES) {
    const all = r.recipes.map((x) => `${x.number} ${x.name}${x.problem ? " (NOT CALIBRATED)" : ""}`);
    return `${active} (of ${all.join(", ")})`;
  }
  const bad = r.recipes.filter((x) => x.problem).length;
  return `${active} (of ${r.recipes.length} recipes${bad ? `; ${bad} NOT CALIBRATED` : ""})`;
}

function showRecipes(r) {
  if (!r) return;
  $("recipes-summary").textContent = `Recipes (${r.recipes.length})`;
  $("recipes").replaceChildren(...r.recipes.map((x) => {
    const li = document.createElement("li");
    li.textContent = `${x.number} ${x.name}: ${x.object}` + (x.problem ? ` — NOT CALIBRATED: ${x.problem}` : "") +
      (x.number === r.active ? " (active)" : "");
    return li;
  }));
}

function showStatus(s) {
  lastStatus = s;
  $("run-state").textContent = `pid ${s.pid}: ${s.run_state}, ${s.state}` +
    (s.calibrated ? "" : ", NOT CALIBRATED") + (s.healthy ? "" : `, UNHEALTHY: ${s.health_problem}`);
  $("recipe").textContent = recipeText(s.recipe);
  $("recipe").title = (s.recipe?.recipes || []).map((x) => `${x.number} ${x.name}`).join(", ");
  showRecipes(s.recipe);
  const rc = s.recalibrate;
  const warn = $("recalibrate");
  warn.hidden = !(rc && rc.warning);
  if (rc && rc.warning) {
    warn.textContent = `RECALIBRATE: ${rc.above} of the last ${rc.jobs} stereo jobs above ` +
      `${rc.threshold_px} px (share ${fmt(rc.share, 2)} > ${rc.share_limit})`;
  }
  $("link-table").tBodies[0].replaceChildren(...s.links.map((l) => cells([
    l.name, l.state, l.peer, l.peers, l.reconnects,
    Object.entries(l.refusals || {}).map(([k, v]) => `${k} ${v}`).join(", "), l.last_error || ""])));
  const counts = Object.entries(s.counters).map(([k, v]) => `${k} ${v}`).join(", ") || "none";
  const cyc = s.cycle_ms.window ? `; cycle p50 ${fmt(s.cycle_ms.p50)} ms, p95 ${fmt(s.cycle_ms.p95)} ms, ` +
    `max ${fmt(s.cycle_ms.max)} ms over ${s.cycle_ms.window} jobs` : "";
  const pl = s.pick_list;
  const pick = pl && pl.instances ? `; pick list of job ${pl.job_id} (${pl.link}): ` +
    (pl.index > pl.count ? `used up (${pl.count} handed out)` : `${pl.index} of ${pl.count} shown`) : "";
  $("counters").textContent = counts + cyc + pick;
  drawBelts(s.conveyor || {});
  const cal = [`calibrated: ${s.calibrated ? "yes" : "NO"}`];
  if (rc && rc.jobs) {
    cal.push(`epipolar: ${rc.above} of the last ${rc.jobs} stereo jobs above ${rc.threshold_px} px ` +
      `(share ${fmt(rc.share, 2)}, warning above ${rc.share_limit} once ${rc.min_jobs} jobs are in)` +
      (rc.warning ? ` — RECALIBRATE for ${fmt(rc.since_s, 0)} s` : ""));
  }
  $("calibration").textContent = cal.join("; ");
  const web = s.web || {};
  $("actions-off").hidden = web.trigger || web.support_bundle;
  $("actions-on").hidden = !(web.trigger || web.support_bundle);
  $("btn-trigger").hidden = !web.trigger;
  $("btn-bundle").hidden = !web.support_bundle;
  $("tuning-off").hidden = !!web.config_edit;
  $("btn-save").hidden = $("btn-reload").hidden = $("btn-try").hidden = !web.config_edit;
  $("btn-try-grab").hidden = !web.config_edit;
  $("btn-shot").hidden = $("btn-teach-save").hidden = $("btn-teach-clear").hidden = !web.config_edit;
  if (web.config_edit) { $("actions-off").hidden = true; $("actions-on").hidden = false; }
}

// --- live cameras: off until ticked; the daemon bounds the grabs whatever the pages ask -----
let liveTimer = null;
async function liveTick() {
  const n = (lastStatus?.last_job && jobs[0]?.views?.length) || (jobs[0]?.stereo === false ? 1 : 2);
  const box = $("live-images");
  while (box.children.length < n) {
    const img = document.createElement("img");
    img.id = `live-${box.children.length}`;
    img.alt = `camera ${box.children.length} live`;
    box.append(img);
  }
  const stamp = Date.now();
  [...box.children].forEach((img, j) => { img.src = `/api/cameras/${j}/preview.jpg?t=${stamp}`; });
  try {
    const c = await getJSON("/api/cameras");
    $("live-figures").textContent = c.figures.map((f, j) => `camera ${j}: focus ${fmt(f.focus, 0)}, ` +
      `over-exposed ${fmt(100 * f.saturated_share, 2)} %, marks seen ${f.marks}`).join("; ") +
      (c.age_s !== null ? ` (picture ${fmt(c.age_s, 1)} s old)` : "");
  } catch (err) { $("live-figures").textContent = err.message; }
}
$("live-on").addEventListener("change", () => {
  clearInterval(liveTimer);
  liveTimer = $("live-on").checked ? setInterval(liveTick, 500) : null;
  if (liveTimer) liveTick();
});

// Exposure and gain: applied live between jobs, then kept in the config's include (token).
async function loadCamSettings() {
  const c = await getJSON("/api/cameras/settings");
  for (const k of ["exposure_us", "gain_db"]) if (c[k] !== null) $(`cam-${k}`).value = c[k];
  $("btn-cam-set").hidden = !c.enabled;
}
$("btn-cam-set").addEventListener("click", async () => {
  const body = {};
  for (const k of ["exposure_us", "gain_db"]) if ($(`cam-${k}`).value !== "") body[k] = Number($(`cam-${k}`).value);
  const headers = { Authorization: `Bearer ${$("token").value}`, "Content-Type": "application/json" };
  try {
    const resp = await fetch(`/api/cameras/${$("cam-j").value}/settings`,
      { method: "POST", headers, body: JSON.stringify(body) });
    const text = await resp.text();
    const ok = resp.ok;
    const out = ok ? JSON.parse(text) : null;
    $("cam-result").textContent = ok ? `APPLIED: read back ${JSON.stringify(out.read_back)}; ${out.saved.message}`
      : `REFUSED (${resp.status}): ${text}`;
    $("cam-result").className = ok ? "status ok" : "status bad";
  } catch (err) { $("cam-result").textContent = err.message; }
  loadCamSettings().catch(() => {});
  loadAudit().catch(() => {});
});
loadCamSettings().catch(() => {});

// --- calibration health: files and the cell drawn from above and from the side -------------
const SVGNS = "http://www.w3.org/2000/svg";
function svgNode(tag, attrs, text) {
  const n = document.createElementNS(SVGNS, tag);
  for (const [k, v] of Object.entries(attrs)) n.setAttribute(k, v);
  if (text !== undefined) n.textContent = text;
  return n;
}

// Camera labels beside their dots without covering each other: cameras of one rig are often a
// few pixels apart in a view. Each label takes the first free slot above or below its dot
// (estimated box: 6 px per character, 12 px high); a label moved off its dot gets a leader.
function placeLabels(labels, W, H) {
  const boxes = [], out = [];
  const overlaps = (b) => boxes.some((o) => b.x < o.x + o.w && o.x < b.x + b.w && b.y < o.y + o.h && o.y < b.y + b.h);
  for (const l of [...labels].sort((p, q) => p.y - q.y)) {
    const w = 6 * l.text.length, h = 12;
    let box = null;
    for (let k = 0; k < 2 * labels.length + 2; k++) {
      const dy = (k % 2 ? 1 : -1) * (6 + 13 * Math.floor(k / 2));  // -6, +6, -19, +19, ...
      const x = Math.min(Math.max(l.x + 6, 0), W - w);
      const b = { x, y: l.y + dy - (dy < 0 ? h : 0), w, h };
      if (!overlaps(b) && b.y >= 0 && b.y + h <= H) { box = b; break; }
    }
    box = box || { x: Math.min(l.x + 6, W - w), y: Math.max(l.y - 6 - h, 0), w, h };
    boxes.push(box);
    if (Math.abs(box.y + h / 2 - l.y) > h) {
      out.push(svgNode("line", { x1: l.x, y1: l.y, x2: box.x, y2: box.y + h / 2, stroke: "#bbb" }));
    }
    out.push(svgNode("text", { x: box.x, y: box.y + h - 2, "font-size": 10, class: "cell-label" }, l.text));
  }
  return out;
}

// Draw the cell projected on axes (a, b) of the base frame: 0 = x, 1 = y, 2 = z.
function drawCell(svg, g, a, b) {
  const pts = [];
  for (const c of g.cameras) pts.push(c.position_mm);
  if (g.reference) pts.push(g.reference.position_mm);
  if (g.last) pts.push(g.last.position_mm);
  pts.push([0, 0, 0]);  // the robot base
  const W = 400, H = 300, M = 30;
  const xs = pts.map((p) => p[a]), ys = pts.map((p) => p[b]);
  const span = Math.max(Math.max(...xs) - Math.min(...xs), Math.max(...ys) - Math.min(...ys), 100) * 1.3;
  const cx = (Math.max(...xs) + Math.min(...xs)) / 2, cy = (Math.max(...ys) + Math.min(...ys)) / 2;
  const k = Math.min(W - 2 * M, H - 2 * M) / span;
  const X = (p) => W / 2 + (p[a] - cx) * k, Y = (p) => H / 2 - (p[b] - cy) * k;
  const parts = [svgNode("circle", { cx: X([0, 0, 0]), cy: Y([0, 0, 0]), r: 4, fill: "#888" }),
    svgNode("text", { x: X([0, 0, 0]) + 6, y: Y([0, 0, 0]) + 4, "font-size": 10 }, "base")];
  const reach = span * 0.25;
  const labels = [];
  for (const c of g.cameras) {
    const p = c.position_mm, ax = c.axis;
    const tip = [0, 1, 2].map((i) => p[i] + ax[i] * reach);
    const half = (c.fov_deg[0] * Math.PI) / 360;
    const dx = tip[a] - p[a], dy = tip[b] - p[b];
    const rot = (ang) => [p[a] + dx * Math.cos(ang) - dy * Math.sin(ang), p[b] + dx * Math.sin(ang) + dy * Math.cos(ang)];
    const [l, r] = [rot(half), rot(-half)];
    const L = [0, 0, 0], R = [0, 0, 0];
    L[a] = l[0]; L[b] = l[1]; R[a] = r[0]; R[b] = r[1];
    parts.push(svgNode("polygon", { points: `${X(p)},${Y(p)} ${X(L)},${Y(L)} ${X(R)},${Y(R)}`,
      fill: "rgba(31,111,208,0.12)", stroke: "none" }));
    parts.push(svgNode("line", { x1: X(p), y1: Y(p), x2: X(tip), y2: Y(tip), stroke: "#1f6fd0" }));
    parts.push(svgNode("circle", { cx: X(p), cy: Y(p), r: 4, fill: "#1f6fd0", class: "cell-camera" }));
    labels.push({ x: X(p), y: Y(p), text: `${c.name} (${c.rig})` });
  }
  parts.push(...placeLabels(labels, W, H));
  if (g.reference) {
    const p = g.reference.position_mm;
    parts.push(svgNode("rect", { x: X(p) - 5, y: Y(p) - 5, width: 10, height: 10, fill: "#070", class: "cell-reference" }));
  }
  if (g.last) {
    const p = g.last.position_mm;
    parts.push(svgNode("path", { d: `M${X(p) - 6},${Y(p)}h12M${X(p)},${Y(p) - 6}v12`, stroke: "#d07a1f", "stroke-width": 2 }));
  }
  svg.replaceChildren(...parts);
}

async function loadCalibration() {
  const c = await getJSON("/api/calibration");
  $("cal-files").tBodies[0].replaceChildren(...c.files.map((f) => cells([
    f.file, f.sets.join(", "), f.modified || f.error || "",
    Object.entries(f.about).map(([k, v]) => `${k} ${typeof v === "number" ? fmt(v, 3) : JSON.stringify(v)}`).join("; ")])));
  drawCell($("cell-top"), c.geometry, 0, 1);
  drawCell($("cell-side"), c.geometry, 0, 2);
  if (c.geometry.note) $("cell-note").textContent += ` (${c.geometry.note})`;
}

// --- tuning, reload and the audit (docs/web.md, "Reload, tuning and audit") ---------------
const TUNED = ["min_contrast", "min_circularity", "min_features", "epipolar_tolerance_px", "model_tolerance_mm"];

async function loadTuning() {
  const t = await getJSON("/api/tuning");
  for (const k of TUNED) $(`t-${k}`).value = t.vision[k];
  [$("t-wd-near").value, $("t-wd-far").value] = t.vision.working_distance_mm;
  $("t-polarity").value = t.polarity || "";
}

async function loadAudit() {
  const a = await getJSON("/api/audit");
  $("audit").tBodies[0].replaceChildren(...a.entries.map((e) => cells([
    e.time, e.source, e.applied ? e.message : `REFUSED: ${e.message}`, e.diff.join("\n")])));
}

function tuningEdit() {
  const vision = {};
  for (const k of TUNED) vision[k] = Number($(`t-${k}`).value);
  vision.working_distance_mm = [Number($("t-wd-near").value), Number($("t-wd-far").value)];
  const body = { vision };
  if ($("t-polarity").value) body.polarity = $("t-polarity").value;
  return body;
}

async function commission(url, body) {
  $("tuning-result").textContent = "judging the config (as vgripd check does)…";
  const headers = { Authorization: `Bearer ${$("token").value}`, "Content-Type": "application/json" };
  try {
    const resp = await fetch(url, { method: "POST", headers, body: body ? JSON.stringify(body) : undefined });
    const text = await resp.text();
    let out;
    try { out = JSON.parse(text); } catch { out = { applied: false, message: `${resp.status} ${text}` }; }
    $("tuning-result").textContent = (out.applied ? "APPLIED: " : "REFUSED: ") + out.message;
    $("tuning-result").className = out.applied ? "status ok" : "status bad";
  } catch (err) { $("tuning-result").textContent = err.message; }
  await Promise.all([loadTuning(), loadAudit()]).catch(() => {});
}

$("btn-save").addEventListener("click", () => commission("/api/tuning", tuningEdit()));

// Teaching: the shots' mean against the reference taught now, and the save.
function teachText(t) {
  if (!t.shots.length) return `recipe ${t.recipe}: no shots yet`;
  const xyz = t.mean.translation_mm.map((v) => fmt(v, 2)).join(", ");
  const from = t.from_taught_mm === null ? "nothing taught yet" :
    `${fmt(t.from_taught_mm, 2)} mm / ${fmt(t.from_taught_deg, 3)} deg from the taught reference`;
  return `recipe ${t.recipe}: ${t.shots.length} shot(s) (jobs ${t.shots.join(", ")}): mean at [${xyz}] mm, ` +
    `spread ${fmt(t.spread_mm, 3)} mm / ${fmt(t.spread_deg, 4)} deg; ${from}`;
}

async function teachAction(url) {
  const headers = { Authorization: `Bearer ${$("token").value}` };
  try {
    const resp = await fetch(url, { method: "POST", headers });
    const text = await resp.text();
    let t;
    try { t = JSON.parse(text); } catch { $("teach-result").textContent = `${resp.status} ${text}`; return; }
    if ("applied" in t) {
      $("teach-result").textContent = (t.applied ? "SAVED: " : "REFUSED: ") + t.message;
    } else {
      $("teach-result").textContent = (t.refused ? `REFUSED: ${t.refused}; ` : "") + teachText(t);
    }
  } catch (err) { $("teach-result").textContent = err.message; }
  loadAudit().catch(() => {});
}
$("btn-shot").addEventListener("click", () => teachAction("/api/teach/shot"));
$("btn-teach-save").addEventListener("click", () => teachAction("/api/teach/save"));
$("btn-teach-clear").addEventListener("click", () => teachAction("/api/teach/clear"));

// A trial: the edited pipeline on the last job's images; every candidate drawn with its fate.
async function tryTuning(grab) {
  $("trial-result").textContent = "running the pipeline with these values…";
  const headers = { Authorization: `Bearer ${$("token").value}`, "Content-Type": "application/json" };
  try {
    const body = { ...tuningEdit(), ...(grab ? { grab: true } : {}) };
    const resp = await fetch("/api/tuning/try", { method: "POST", headers, body: JSON.stringify(body) });
    const text = await resp.text();
    let t;
    try { t = JSON.parse(text); } catch { t = { status: null, message: `${resp.status} ${text}` }; }
    if (!t.trial) { $("trial-result").textContent = `TRIAL REFUSED: ${t.message}`; return; }
    const fates = t.candidates.map((c) => `${c.image}: ` + Object.entries(c).filter(([k]) => k !== "image")
      .map(([k, v]) => `${v} ${k}`).join(", ")).join("; ");
    const on = t.job_id === null ? "a fresh grab" : `job ${t.job_id}`;
    $("trial-result").textContent = `TRIAL ${t.trial} on ${on}: ${t.status} ${t.message}` +
      (fates ? ` (candidates: ${fates})` : "");
    $("trial-causes").replaceChildren(...t.causes.map((c) => {
      const li = document.createElement("li");
      li.textContent = `${c.key}: ${c.reason}`;
      return li;
    }));
    $("trial-images").replaceChildren(...t.images.map((src, k) => {
      const img = document.createElement("img");
      img.src = src;
      img.alt = `trial ${t.trial} camera ${k}`;
      img.id = `trial-img-${k}`;
      return img;
    }));
  } catch (err) { $("trial-result").textContent = err.message; }
}
$("btn-try").addEventListener("click", () => tryTuning(false));
$("btn-try-grab").addEventListener("click", () => tryTuning(true));
$("btn-reload").addEventListener("click", () => commission("/api/reload"));

async function loadRegisters() {
  const views = await getJSON("/api/registers");
  $("registers").replaceChildren(...views.map((v) => {
    const div = document.createElement("div");
    const h = document.createElement("h3");
    h.textContent = `Register map of ${v.link} (as the PLC reads it; ${v.word_order}, ${v.value_format})`;
    const table = document.createElement("table");
    table.append(cells(["addr", "name", "words", "value", "meaning"]));
    for (const r of v.rows) {
      table.append(cells([r.address, r.name, r.words.join(" "),
        typeof r.value === "number" && !Number.isInteger(r.value) ? fmt(r.value, 4) : r.value, r.meaning]));
    }
    div.append(h, table);
    return div;
  }));
}

async function refresh() {
  try {
    const s = await getJSON("/api/status");
    showStatus(s);
    // Polled while the stream is down: a job the page has not seen reloads the history.
    if (pollTimer !== null && s.last_job && s.last_job.id !== jobs[0]?.id) await loadJobs();
  } catch (err) {
    $("run-state").textContent = `daemon not reachable (${err.message})`;
  }
}

async function action(url, opts) {
  const headers = { Authorization: `Bearer ${$("token").value}` };
  const resp = await fetch(url, { ...opts, headers });
  if (!resp.ok) throw new Error(`${resp.status} ${await resp.text()}`);
  return resp;
}

$("btn-trigger").addEventListener("click", async () => {
  $("action-result").textContent = "triggered…";
  try {
    const r = await (await action("/api/trigger", { method: "POST" })).json();
    $("action-result").textContent = `test job ${r.job_id}: ${r.status} ${r.message}`;
  } catch (err) { $("action-result").textContent = err.message; }
});

$("btn-bundle").addEventListener("click", async () => {
  try {
    const resp = await action("/api/support-bundle", {});
    const name = (resp.headers.get("Content-Disposition") || "").match(/filename="(.+)"/)?.[1] || "vgripd-support.zip";
    const a = document.createElement("a");
    a.href = URL.createObjectURL(await resp.blob());
    a.download = name;
    a.click();
    URL.revokeObjectURL(a.href);
  } catch (err) { $("action-result").textContent = err.message; }
});

async function loadJobs() {
  jobs = await getJSON("/api/jobs");
  if (jobs.length) showJob(jobs[0]);
  showHistory();
}

// Live updates: the daemon pushes the status document and each job over one event stream.
// While the stream fails the page asks /api/status every POLL_MS instead; EventSource
// reconnects by itself (a stream refused outright is opened again after REOPEN_MS). Every
// (re)connection reloads the history first, so a job that finished while it was down is not
// missed. body[data-live] says which way the page is fed: "events" or "polling".
const POLL_MS = 2000;
const REOPEN_MS = 10000;
let pollTimer = null;

function feedBy(how) {
  document.body.dataset.live = how;
  if (how === "events") {
    clearInterval(pollTimer);
    pollTimer = null;
  } else if (pollTimer === null) {
    pollTimer = setInterval(refresh, POLL_MS);
  }
}

function connectEvents() {
  const events = new EventSource("/api/events");
  events.addEventListener("open", () => { feedBy("events"); loadJobs().catch(() => {}); });
  events.addEventListener("error", () => {
    feedBy("polling");
    if (events.readyState === EventSource.CLOSED) setTimeout(connectEvents, REOPEN_MS);
  });
  events.addEventListener("status", (e) => showStatus(JSON.parse(e.data)));
  events.addEventListener("job", (e) => {
    const job = JSON.parse(e.data);
    jobs.unshift(job);
    jobs.length = Math.min(jobs.length, lastStatus?.web?.history ?? 100);
    showJob(job);
    showHistory();
    loadCalibration().catch(() => {});  // the last pose in the drawings
  });
  events.addEventListener("links", () => { loadRegisters().catch(() => {}); });
}

async function main() {
  await refresh();
  try {
    await loadJobs();
    $("config-text").textContent = JSON.stringify(await getJSON("/api/config"), null, 2);
    await loadRegisters();
    await loadTuning();
    await loadAudit();
    await loadCalibration();
  } catch (err) { console.error(err); }
  // The stream opens once the page has drawn what is there (a headless browser dumping the
  // page after a virtual-time budget sees it complete; the open event catches up anyway).
  setTimeout(connectEvents, 1000);
  setInterval(() => loadRegisters().catch(() => {}), 2000);
}

main();

// --- conveyor: each conveyor recipe's belt from above, travel to the right: the pick window
// shaded, each queued part where the queue predicts it at the newest count (a dot and a tick
// for its rotation). Data: /api/status "conveyor" (docs/conveyor.md, "The belt strip").
function drawBelts(conveyor) {
  const box = $("belts");
  const entries = Object.entries(conveyor);
  box.hidden = entries.length === 0;
  const keep = new Set(entries.map(([n]) => `belt-${n}`));
  for (const fig of [...box.children]) if (!keep.has(fig.id)) fig.remove();
  for (const [n, c] of entries) {
    let fig = $(`belt-${n}`);
    if (!fig) {
      fig = document.createElement("figure");
      fig.id = `belt-${n}`;
      fig.className = "belt";
      fig.append(svgNode("svg", { viewBox: "0 0 800 120", role: "img",
        "aria-label": `conveyor of recipe ${n}: queued parts and the pick window` }),
      document.createElement("figcaption"));
      box.append(fig);
    }
    drawBelt(fig.querySelector("svg"), c);
    fig.querySelector("figcaption").textContent = `Conveyor of recipe ${n}: ${c.queued} queued ` +
      `at count ${c.last_count ?? "(none yet)"}, pick window ${c.window_mm[0]} .. ${c.window_mm[1]} mm ` +
      `along the belt (travel to the right); seen ${c.seen}, duplicates ${c.duplicates}, ` +
      `served ${c.served}, dropped ${c.dropped}; latch ${c.latch}` +
      (c.queue_latency_ms_p50 == null ? "" : `, exposure -> queue p50 ${fmt(c.queue_latency_ms_p50)} ms`);
  }
}

function drawBelt(svg, c) {
  const W = 800, H = 120, M = 20;
  const [w0, w1] = c.window_mm;
  const along = c.parts.map((p) => p.along_mm);
  const span = w1 - w0;
  const lo = Math.min(w0 - 0.5 * span, ...along.map((a) => a - 60));
  const hi = Math.max(w1 + 0.1 * span, ...along.map((a) => a + 60));
  const half = Math.max(100, ...c.parts.map((p) => Math.abs(p.across_mm) + 60));
  const x = (a) => M + (a - lo) / (hi - lo) * (W - 2 * M);
  const y = (across) => H / 2 - across / half * (H / 2 - 10);  // left of the travel: up
  const r = Math.max(4, 40 / (hi - lo) * (W - 2 * M));
  const parts = [
    svgNode("rect", { class: "belt-surface", x: M, y: 10, width: W - 2 * M, height: H - 20 }),
    svgNode("rect", { class: "belt-window", x: x(w0), y: 10, width: x(w1) - x(w0), height: H - 20 }),
    svgNode("text", { x: x(w0) + 3, y: H - 14, class: "belt-label" }, `window ${w0}`),
    svgNode("text", { x: x(w1) - 3, y: H - 14, class: "belt-label", "text-anchor": "end" }, `${w1} mm`),
    svgNode("path", { class: "belt-arrow", d: `M${W - M - 40},18 h30 m-6,-4 l6,4 l-6,4` }),
  ];
  for (const p of c.parts) {
    const g = svgNode("g", { class: "belt-part", "data-uid": p.uid, "data-along": p.along_mm,
      transform: `translate(${x(p.along_mm).toFixed(1)},${y(p.across_mm).toFixed(1)}) rotate(${-p.theta_deg})` });
    g.append(svgNode("circle", { r: r.toFixed(1) }),
      svgNode("line", { x1: 0, y1: 0, x2: (r * 1.4).toFixed(1), y2: 0 }),
      svgNode("title", {}, `part ${p.uid} (job ${p.job_id}, seen ${p.sightings}x): ` +
        `${fmt(p.along_mm)} mm along, ${fmt(p.across_mm)} mm across, ${fmt(p.theta_deg)} deg`));
    parts.push(g);
  }
  svg.replaceChildren(...parts);
}
