// The walked hand-eye calibration pages (handeye-plan.html, handeye-walk.html): vanilla JS,
// no build step. Actions carry the token as "Authorization: Bearer"; the server judges.
"use strict";
const $ = (id) => document.getElementById(id);
const SVG = "http://www.w3.org/2000/svg";

function headers() {
  return { Authorization: `Bearer ${$("token").value}`, "Content-Type": "application/json" };
}

async function post(url, body) {
  const resp = await fetch(url, { method: "POST", headers: headers(), body: JSON.stringify(body ?? {}) });
  const text = await resp.text();
  let data;
  try { data = JSON.parse(text); } catch { data = { refused: text }; }
  return { ok: resp.ok, status: resp.status, data };
}

function cell(row, text) {
  const td = document.createElement("td");
  td.textContent = text;
  row.appendChild(td);
}

// --- plan page ---------------------------------------------------------------------------

function planForm(save) {
  return {
    mode: $("mode").value, board: $("board").value, around: $("around").value,
    box: `${$("travel").value} ${$("tilt").value}`, count: $("count").value,
    distance: $("distance").value, board_offset: $("board-offset").value,
    save: save ? $("save").value : null,
  };
}

function drawPath(poses) {
  const svg = $("plan-path");
  while (svg.firstChild) svg.removeChild(svg.firstChild);
  if (!poses.length) return;
  const xyz = poses.map((p) => [0, 1, 2].map((i) => p.matrix_mm[i][3]));
  const views = [[0, 1, 0, "top (x, y)"], [0, 2, 320, "side (x, z)"]];
  for (const [a, b, left, title] of views) {
    const us = xyz.map((p) => p[a]), vs = xyz.map((p) => p[b]);
    const span = Math.max(Math.max(...us) - Math.min(...us), Math.max(...vs) - Math.min(...vs), 1);
    const u0 = (Math.max(...us) + Math.min(...us)) / 2, v0 = (Math.max(...vs) + Math.min(...vs)) / 2;
    const px = (u, v) => [left + 160 + (u - u0) / span * 260, 160 - (v - v0) / span * 260];
    const line = document.createElementNS(SVG, "polyline");
    line.setAttribute("points", xyz.map((p) => px(p[a], p[b]).join(",")).join(" "));
    line.setAttribute("fill", "none");
    line.setAttribute("stroke", "#888");
    svg.appendChild(line);
    xyz.forEach((p, k) => {
      const [x, y] = px(p[a], p[b]);
      const dot = document.createElementNS(SVG, "circle");
      dot.setAttribute("cx", x); dot.setAttribute("cy", y); dot.setAttribute("r", k ? 3 : 5);
      dot.setAttribute("fill", k ? "#2060c0" : "#c02020");
      svg.appendChild(dot);
    });
    const label = document.createElementNS(SVG, "text");
    label.setAttribute("x", left + 8); label.setAttribute("y", 16);
    label.textContent = title;
    svg.appendChild(label);
  }
}

function showPlan(data) {
  const poses = data.poses ?? [];
  const format = data.pose_format ?? "";
  const head = $("plan-poses").querySelector("thead");
  head.textContent = "";
  const hr = document.createElement("tr");
  for (const t of ["#", `pose (${format})`, "board in image (px)"]) {
    const th = document.createElement("th"); th.textContent = t; hr.appendChild(th);
  }
  head.appendChild(hr);
  const body = $("plan-poses").querySelector("tbody");
  body.textContent = "";
  for (const p of poses) {
    const row = document.createElement("tr");
    cell(row, String(p.index));
    cell(row, (p[format] ?? []).map((v) => Number(v).toFixed(4)).join(" "));
    cell(row, (p.board_px ?? []).map((v) => Number(v).toFixed(0)).join(" "));
    body.appendChild(row);
  }
  drawPath(poses);
  if (data.drawing) {
    $("plan-drawing").src = `/api/handeye/plan.png?t=${Date.now()}`;
    $("plan-drawing").hidden = false;
  }
}

async function plan(save) {
  $("plan-result").textContent = save ? "planning and saving…" : "planning…";
  const { ok, data } = await post("/api/handeye/plan", planForm(save));
  const c = data.condition ?? {};
  if (!ok) {
    $("plan-result").textContent = `REFUSED: ${data.refused ?? "?"}`;
  } else {
    $("plan-result").textContent = `PLAN: ${(data.poses ?? []).length} poses, condition ` +
      `${Number(c.condition).toPrecision(3)}, effective rotation ${Number(c.effective_deg).toFixed(1)} deg` +
      (data.saved ? `; saved as ${data.saved}` : "; dry run, nothing written");
  }
  showPlan(data);
}

// --- walk page ---------------------------------------------------------------------------

function showWalk(w) {
  if (!w) return;
  const counts = w.targets === undefined ? "" :
    `${w.targets} targets: seen ${w.seen}, not seen ${w.not_seen}, unreachable ${w.unreachable}` +
    (w.index === null || w.index === undefined ? "" : `; next target ${w.index}`);
  $("walk-state").textContent = `WALK ${w.state.toUpperCase()}` + (w.link ? ` on ${w.link}` : "") +
    (w.plan ? ` (${w.plan})` : "") + (w.message ? `: ${w.message}` : "") + (w.solving ? "; solving…" : "");
  $("walk-counts").textContent = counts;
  const body = $("walk-targets").querySelector("tbody");
  body.textContent = "";
  for (const r of w.records ?? []) {
    const row = document.createElement("tr");
    row.className = r.status;
    cell(row, String(r.target)); cell(row, r.status); cell(row, String(r.corners)); cell(row, r.reason);
    body.appendChild(row);
  }
  const s = w.solution;
  if (s) {
    $("walk-solution").textContent = s.ok ? JSON.stringify({ file: s.file, rms_px: s.summary?.rms_px,
      stability: s.summary?.stability, plan: s.summary?.plan }, null, 1) : s.reason;
  }
}

async function refreshWalk() {
  const resp = await fetch("/api/handeye");
  if (!resp.ok) return;
  const data = await resp.json();
  const select = $("link");
  if (!select.options.length) {
    for (const l of data.links) {
      const o = document.createElement("option");
      o.value = String(l.index); o.textContent = `${l.index}: ${l.type}`;
      select.appendChild(o);
    }
  }
  if (data.plan?.saved && !$("plan").dataset.touched) $("plan").value = data.plan.saved;
  showWalk(data.walk);
}

async function walkAction(path, body, what) {
  $("walk-result").textContent = `${what}…`;
  const { ok, data } = await post(path, body);
  if (!ok) {
    $("walk-result").textContent = `REFUSED: ${data.refused ?? data.message ?? data.solution?.reason ?? "?"}`;
  } else {
    $("walk-result").textContent = `${what.toUpperCase()}: ${data.message ?? data.state ?? "done"}`;
  }
  if (data.state) showWalk(data);
  else await refreshWalk();
}

// --- wiring ------------------------------------------------------------------------------

if (document.body.dataset.page === "plan") {
  $("btn-dry").addEventListener("click", () => plan(false));
  $("btn-save").addEventListener("click", () => plan(true));
  fetch("/api/handeye").then((r) => r.ok ? r.json() : null).then((d) => {
    if (d) $("vendor").textContent = d.vendor;
  });
} else {
  $("plan").addEventListener("input", () => { $("plan").dataset.touched = "1"; });
  $("btn-start").addEventListener("click", () => walkAction("/api/handeye/walk/start",
    { plan: $("plan").value, link: Number($("link").value || 0) }, "started"));
  $("btn-stop").addEventListener("click", () => walkAction("/api/handeye/walk/stop", {}, "stopped"));
  $("btn-solve").addEventListener("click", () => walkAction("/api/handeye/solve", {}, "solved"));
  $("btn-accept").addEventListener("click", () => walkAction("/api/handeye/accept",
    { set_aside_references: $("set-aside").checked }, "accepted"));
  refreshWalk();
  const events = new EventSource("/api/events");
  events.addEventListener("walk", (e) => showWalk(JSON.parse(e.data)));
}
