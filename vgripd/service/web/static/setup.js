// The guided setup (docs/setup.md): one section per step, the server keeps what is done.
"use strict";

const $ = (id) => document.getElementById(id);
let state = null;
let step = "cameras";
let previewTimer = null;
window.setupActions = 0;  // page actions (clicks and form submits) counted for the bench

$("token").value = sessionStorage.getItem("vgripd-token") || "";
$("token").addEventListener("change", () => sessionStorage.setItem("vgripd-token", $("token").value));

function headers(json) {
  const h = { Authorization: `Bearer ${$("token").value}` };
  if (json) h["Content-Type"] = "application/json";
  return h;
}

// A request's answer as {ok, status, data}: JSON when it is, else the text as data.message.
async function call(method, url, body) {
  const resp = await fetch(url, { method, headers: headers(body !== undefined),
                                  body: body === undefined ? undefined : JSON.stringify(body) });
  const text = await resp.text();
  let data;
  try { data = JSON.parse(text); } catch { data = { message: text }; }
  return { ok: resp.ok, status: resp.status, data };
}

function fmt(v, d) { return typeof v === "number" ? v.toFixed(d) : String(v); }
function li(text, cls) { const e = document.createElement("li"); e.textContent = text; if (cls) e.className = cls; return e; }
function img(src, alt) { const e = document.createElement("img"); e.src = src; e.alt = alt; return e; }
function row(cells) {
  const tr = document.createElement("tr");
  for (const c of cells) {
    const td = document.createElement("td");
    if (c instanceof Node) td.append(c); else td.textContent = c;
    tr.append(td);
  }
  return tr;
}
// A button's action, one at a time: clicked again while its request is out (a double click,
// an impatient operator on a busy cell PC), it is greyed and the click does nothing, so no
// requests pile up behind the daemon's lock and hold the browser's few connections.
function act(id, fn) {
  const button = $(id);
  button.addEventListener("click", async (e) => {
    e.preventDefault();
    if (button.disabled) return;
    window.setupActions += 1;
    button.disabled = true;
    try { await fn(); } finally { button.disabled = false; }
  });
}
function outcome(el, r) {
  const d = r.data;
  const applied = d.applied === true;
  el.textContent = (applied ? "APPLIED: " : (d.pending ? "ACCEPTED: " : `REFUSED (${r.status}): `)) +
    (d.message || "");
  el.className = applied || d.pending ? "status ok" : "status bad";
}

// --- steps ------------------------------------------------------------------------------------
async function load() {
  const r = await call("GET", "/api/setup");
  if (!r.ok) { $("setup-note").textContent = `${r.status} ${r.data.message}`; return; }
  state = r.data;
  $("steps").replaceChildren(...state.steps.map((s, i) => {
    const b = document.createElement("button");
    b.id = `nav-${s.id}`;
    b.textContent = `${i + 1}. ${s.title}${s.done ? " \u2713" : ""}`;
    b.className = s.id === step ? "current" : "";
    b.addEventListener("click", () => { window.setupActions += 1; show(s.id); });
    return b;
  }));
  $("setup-note").textContent = state.edit ? "" :
    "Saving needs status.allow_config_edit (and the token): the page only shows.";
  fill();
}

function show(id, keepCheck) {
  step = id;
  for (const s of document.querySelectorAll(".step")) s.hidden = s.id !== `step-${id}`;
  if (!keepCheck) {
    $("check-step").textContent = id;
    $("check-findings").replaceChildren();
    $("check-summary").textContent = "";
  }
  if (previewTimer) { clearInterval(previewTimer); previewTimer = null; }
  if (id === "cameras") { previewTimer = setInterval(previews, 1000); focusState().catch(() => {}); }
  if (id === "link") linkOptions().catch(() => {});
  load().catch(() => {});
}

function fill() {
  const s = state;
  $("cam-describe").textContent = `camera type ${s.camera.type}: ${s.camera.describe}`;
  if (!$("calib-board").value) $("calib-board").value = s.board;
  if (s.capture) coverage(s.capture);
  $("he-current").textContent = heCurrent(s);
  $("btn-he-learning").hidden = !s.learning_hand_eye;
  const pose = s.hand_eye && s.hand_eye.T_base_camera;
  if (pose && !$("he-t").value) {  // a new rig goes live with the pose confirmed again
    $("he-t").value = pose.translation_mm.join(" ");
    $("he-r").value = (pose.rotvec_rad || [0, 0, 0]).join(" ");
  }
  $("link-table").tBodies[0].replaceChildren(...Object.entries(s.links || {}).map(
    ([name, h]) => row([name, h.state, h.peer || "", String((h.peers || []).length ?? "")])));
  $("link-registers").replaceChildren(...(s.registers || []).map((reg) => {
    const t = document.createElement("table");
    const cap = document.createElement("caption");
    cap.textContent = `${reg.link}: register map (${reg.word_order || ""} ${reg.value_format || ""})`;
    t.append(cap, ...reg.rows.slice(0, 40).map((r) => row([String(r.address), r.name, String(r.value ?? ""), r.meaning || ""])));
    return t;
  }));
}

// What the hand-eye step does with the accepted calibration (a cameras result: the reference
// camera's pose places them all).
function heCurrent(s) {
  const p = s.pending;
  if (p && p.kind === "cameras" && p.placed)
    return `the accepted calibration places its ${p.cameras.length} cameras (${p.cameras.join(", ")}) in the base frame already: Save writes them as [[calibration.cameras]] (the pose fields are not used)`;
  if (p && p.kind === "cameras")
    return `the accepted calibration holds ${p.cameras.length} cameras (${p.cameras.join(", ")}) relative to ${p.reference}: ` +
      `enter ${p.reference}'s pose in the robot base frame; Save places every camera by it ` +
      `(T_base_camera = T_base_${p.reference} @ T_${p.reference}_camera) and writes them as [[calibration.cameras]], judged as one transaction`;
  if (s.pending_calibration) return "the accepted calibration waits for this pose";
  return s.hand_eye ? `now: ${JSON.stringify(s.hand_eye)}` : "no hand-eye yet";
}

async function previews() {
  const imgs = [];
  for (let j = 0; j < 2; j++) {
    const e = img(`/api/cameras/${j}/preview.jpg?t=${Date.now()}`, `camera ${j}`);
    e.addEventListener("error", () => e.remove());  // a camera with one image
    imgs.push(e);
  }
  $("cam-previews").replaceChildren(...imgs);
}

// --- 1 cameras --------------------------------------------------------------------------------
$("cam-form").addEventListener("submit", async (e) => {
  e.preventDefault();
  window.setupActions += 1;
  const body = {};
  if ($("cam-exposure").value) body.exposure_us = Number($("cam-exposure").value);
  if ($("cam-gain").value) body.gain_db = Number($("cam-gain").value);
  const r = await call("POST", "/api/cameras/0/settings", body);
  $("cam-result").textContent = r.ok ? `applied: ${JSON.stringify(r.data.read_back)}; ${r.data.saved.message}` :
    `REFUSED (${r.status}): ${r.data.message}`;
});

// The lens focus where the camera has a focus control; else the reason it has none.
function showFocus(d) {
  if (!d.available) {
    $("cam-focus-state").textContent = `not available: ${d.reason}`;
    $("cam-focus-form").hidden = true;
    return;
  }
  $("cam-focus-state").textContent = d.cameras.map((c) => `${c.name}: ${c.feature} = ${c.value} (${c.range})`).join("; ");
  $("cam-focus-feature").textContent = d.cameras[0].feature;
  if (!$("cam-focus").value) $("cam-focus").value = d.cameras[0].value ?? "";
  $("cam-focus-form").hidden = false;
}
async function focusState() {
  const r = await call("GET", "/api/setup/focus");
  if (r.ok) showFocus(r.data); else $("cam-focus-state").textContent = `${r.status}: ${r.data.message}`;
}
$("cam-focus-form").addEventListener("submit", async (e) => {
  e.preventDefault();
  window.setupActions += 1;
  const r = await call("POST", "/api/setup/focus", { value: Number($("cam-focus").value) });
  if (!r.ok) { $("cam-focus-result").textContent = `REFUSED (${r.status}): ${r.data.message}`; return; }
  showFocus(r.data);
  $("cam-focus-result").textContent = `APPLIED: ${r.data.note}`;
});

// --- 2 calibration ----------------------------------------------------------------------------
function coverage(c) {
  const blocks = c.cameras.map((cam) => {
    const div = document.createElement("div");
    div.className = "coverage";
    const t = document.createElement("table");
    const cells = new Set(cam.cells.map(([x, y]) => `${x},${y}`));
    for (let y = 0; y < cam.grid; y++) {
      const tr = document.createElement("tr");
      for (let x = 0; x < cam.grid; x++) {
        const td = document.createElement("td");
        td.className = cells.has(`${x},${y}`) ? "covered" : "missing";
        td.textContent = cells.has(`${x},${y}`) ? "\u25a0" : "\u00b7";
        tr.append(td);
      }
      t.append(tr);
    }
    const p = document.createElement("p");
    p.textContent = `${cam.name}: ${cam.summary}` + (cam.missing.length ? `; still missing: ${cam.missing.join("; ")}` : "; complete");
    div.append(t, p);
    return div;
  });
  const head = document.createElement("p");
  head.id = "calib-sets";
  head.textContent = `${c.sets} set(s) kept in ${c.folder}`;
  const list = document.createElement("ul");
  list.id = "calib-set-list";
  for (const e of c.manifest || []) {
    const li = document.createElement("li");
    li.textContent = `set ${e.set}: ${e.added}` + (e.flange ? `; flange ${e.flange}` : "; no flange pose");
    list.append(li);
  }
  $("calib-coverage").replaceChildren(head, list, ...blocks);
}

async function grab(keep, auto) {
  const r = await call("POST", "/api/setup/calib/grab", { board: $("calib-board").value, keep, auto });
  if (!r.ok) { $("calib-why").textContent = `${r.status}: ${r.data.message}`; return false; }
  const g = r.data;
  $("calib-why").textContent = g.kept ? g.kept : `grab ${g.grab}: ${g.why}`;
  $("calib-images").replaceChildren(...g.images.map((src, k) => img(src, `corners ${k}`)));
  coverage(g.capture);
  return true;
}
act("btn-calib-grab", () => grab(false, false));
act("btn-calib-keep", () => grab(true, false));
// Auto-capture: one grab after the other while ticked (each is paced by the camera and the
// corner search); a pause only after a refusal. No timer between grabs: a browser slows the
// timers of a page it does not show, not its requests.
let autoRunning = false;
$("calib-auto").addEventListener("change", async () => {
  window.setupActions += 1;
  if (autoRunning) return;
  autoRunning = true;
  try {
    while ($("calib-auto").checked) {
      const ok = await grab(false, true).catch(() => false);
      if (!ok) await new Promise((r) => setTimeout(r, 1000));
    }
  } finally { autoRunning = false; }
});


// The distortion model the calibration chose, and why ([about.model_choice]).
function modelLine(choice) {
  if (!choice || typeof choice !== "object") return `model: ${choice || "not reported"}`;
  return `model: ${choice.model} (${choice.chosen_by}${choice.reason ? `: ${choice.reason}` : ""})`;
}

function calibResult(c) {
  const res = c.result;
  if (!res) {
    $("calib-result").textContent = c.ok === false ? `FAILED: ${c.output}` : "";
    return;
  }
  const std = res.std || {};
  let lines;
  if (res.kind === "cameras") {
    lines = [`RMS ${fmt(res.rms_px, 4)} px; poses relative to ${res.reference}; base frame: ${res.base_frame}`]
      .concat((res.cameras || []).map((cam) => `${cam.name}: RMS ${fmt(cam.rms_px, 4)} px, pose ${JSON.stringify((cam.T_reference_camera || {}).translation_mm)} mm`));
  } else if (res.kind === "intrinsics") {
    lines = [
      `RMS ${fmt(res.rms_px, 4)} px over ${res.images_used} images`,
      `fx ${fmt(res.left.fx, 2)} +- ${fmt(std.fx, 2)}, cx ${fmt(res.left.cx, 2)}, cy ${fmt(res.left.cy, 2)}`,
      modelLine(res.model_choice),
    ];
  } else {
    lines = [
      `RMS ${fmt(res.rms_px, 4)} px over ${res.pairs_used} pairs; epipolar ${JSON.stringify(res.epipolar_px)}`,
      `left fx ${fmt(res.left.fx, 2)} +- ${fmt((std.left || {}).fx, 2)}, cx ${fmt(res.left.cx, 2)}, cy ${fmt(res.left.cy, 2)}`,
      `baseline ${JSON.stringify(res.T_right_left.translation_mm)} mm +- ${JSON.stringify(std.translation_mm)}`,
      modelLine(res.model_choice),
    ];
  }
  if (!res.usable) lines.push(`no base frame yet: Accept, then the hand-eye step places every camera by ${res.reference}'s pose`);
  const p = document.createElement("pre");
  p.id = "calib-figures";
  p.textContent = lines.concat((res.warnings || []).map((w) => `warning: ${w}`)).join("\n");
  const t = document.createElement("table");
  t.id = "calib-pairs";
  const pairs = res.per_pair || [];
  const worst = Math.max(...pairs.map((q) => q.rms_px || 0));
  for (const q of pairs) {
    const box = document.createElement("input");
    box.type = "checkbox";
    const m = /_(\d+)\.png/.exec(q.left || q.name || q.image || "");
    box.dataset.set = m ? String(Number(m[1])) : "";
    if ((q.rms_px || 0) === worst && pairs.length > 3) box.title = "the worst pair";
    t.append(row([box, q.left || q.name || q.image || "", fmt(q.rms_px, 4)]));
  }
  $("calib-result").replaceChildren(p, t);
  $("btn-calib-drop").hidden = false;
  $("btn-calib-accept").hidden = !(res.usable || res.kind === "cameras");
}

async function pollCalibration() {
  for (;;) {  // the server answers when it ends or every few seconds (?wait=1)
    const r = await call("GET", "/api/setup/calib?wait=1");
    const c = r.data;
    if (c.running) {
      $("calib-progress").textContent = `calibrating ${c.sets} sets in a child process: ${fmt(c.elapsed_s, 0)} s (${c.command})`;
      continue;
    }
    $("calib-progress").textContent = c.ok ? `calibrated in ${c.seconds} s` : (c.ok === false ? "calibration failed" : "");
    calibResult(c);
    return;
  }
}
act("btn-calib-run", async () => {
  $("calib-auto").checked = false;
  const r = await call("POST", "/api/setup/calib/run", { kind: $("calib-kind").value });
  if (!r.ok) { $("calib-progress").textContent = `${r.status}: ${r.data.message}`; return; }
  pollCalibration();
});
act("btn-calib-drop", async () => {
  const sets = [...document.querySelectorAll("#calib-pairs input:checked")].map((b) => Number(b.dataset.set));
  const r = await call("POST", "/api/setup/calib/drop", { sets });
  $("calib-accepted").textContent = r.ok ? `put aside: ${r.data.dropped.join(", ")}; calibrate again` : r.data.message;
});
act("btn-calib-accept", async () => {
  const r = await call("POST", "/api/setup/calib/accept");
  outcome($("calib-accepted"), r);
  load().catch(() => {});
});

// --- 3 hand-eye -------------------------------------------------------------------------------
const numbers = (text) => text.split(/[\s,]+/).filter((x) => x).map(Number);
act("btn-he-learning", () => {
  const p = state.learning_hand_eye.T_base_camera;
  $("he-t").value = p.translation_mm.join(" ");
  $("he-r").value = p.rotvec_rad.join(" ");
});
$("he-form").addEventListener("submit", async (e) => {
  e.preventDefault();
  window.setupActions += 1;
  $("he-result").textContent = "judging (as vgripd check does)…";
  const r = await call("POST", "/api/setup/handeye", { translation_mm: numbers($("he-t").value), rotvec_rad: numbers($("he-r").value) });
  outcome($("he-result"), r);
  load().catch(() => {});
});

function solution(c) {
  const res = c.result;
  if (!res) return c.ok === false ? `FAILED: ${c.output}` : "";
  const he = res.hand_eye || {};
  const pose = he.T_flange_camera || he.T_base_camera || {};
  const lines = [
    `${res.mode} (${he.mounting}), ${res.samples} sets, solver ${res.solver}, RMS ${fmt(res.rms_px, 3)} px`,
    `${he.T_flange_camera ? "T_flange_camera" : "T_base_camera"}: ${(pose.translation_mm || []).map((v) => fmt(v, 2)).join(" ")} mm, ` +
      `${(pose.rotvec_rad || []).map((v) => fmt(v, 5)).join(" ")} rad`,
  ];
  if (res.fit_check) lines.push(`fit check: ${res.fit_check.ok ? "OK" : "NOT OK"}, ratio ${fmt(res.fit_check.ratio, 2)}`);
  for (const q of res.per_sample || []) lines.push(`sample ${q.sample} ${q.image}: ${fmt(q.rms_px, 3)} px`);
  return lines.concat((res.warnings || []).map((w) => `warning: ${w}`)).join("\n");
}
async function pollSolve() {
  for (;;) {
    const r = await call("GET", "/api/setup/handeye/solve?wait=1");
    const c = r.data;
    if (c.running) {
      $("he-solve-progress").textContent = `solving from ${c.sets} sets in a child process: ${fmt(c.elapsed_s, 0)} s`;
      continue;
    }
    $("he-solve-progress").textContent = c.ok ? `solved in ${c.seconds} s` : (c.ok === false ? "the solve failed" : "");
    $("he-solve-result").textContent = solution(c);
    $("btn-he-use").hidden = !c.ok;
    return;
  }
}
act("btn-he-solve", async () => {
  $("btn-he-use").hidden = true;
  const r = await call("POST", "/api/setup/handeye/solve", { mode: $("he-mode").value });
  if (!r.ok) { $("he-solve-progress").textContent = `REFUSED (${r.status}): ${r.data.message}`; return; }
  pollSolve();
});
act("btn-he-use", async () => {
  $("he-use-result").textContent = "judging (as vgripd check does)…";
  const r = await call("POST", "/api/setup/handeye/use");
  outcome($("he-use-result"), r);
  load().catch(() => {});
});

// --- 4 object ---------------------------------------------------------------------------------
function markKind(m) {
  if (m.kind === "aruco") return `ArUco #${m.marker_id} (${m.dictionary})`;
  if (m.kind === "template") return `template ${m.label} (score ${fmt(m.score, 2)})`;
  return "circle";
}
// The marks found (and taught) with the pair; a region dragged on the left image fills obj-box.
function showMarks(d) {
  const [left, ...rest] = d.images.map((src, k) => img(src, `marks ${k}`));
  const frame = document.createElement("span");
  frame.className = "draw";
  const box = document.createElement("div");
  box.className = "box";
  box.hidden = true;
  left.id = "obj-left";
  left.dataset.width = String(d.sizes[0][0]);
  left.draggable = false;
  let start = null;
  const at = (e) => {
    // the picture's content box (inside its border), scaled from the camera's pixels
    const r = left.getBoundingClientRect(), s = Number(left.dataset.width) / left.clientWidth;
    return [(e.clientX - r.left - left.clientLeft) * s, (e.clientY - r.top - left.clientTop) * s, 1 / s];
  };
  const drawn = (e) => {
    const [x, y, s] = at(e);
    const x0 = Math.min(start[0], x), y0 = Math.min(start[1], y);
    const w = Math.abs(x - start[0]), h = Math.abs(y - start[1]);
    Object.assign(box.style, { left: `${x0 * s + left.clientLeft}px`, top: `${y0 * s + left.clientTop}px`,
                               width: `${w * s}px`, height: `${h * s}px` });
    box.hidden = false;
    return [x0, y0, w, h].map(Math.round);
  };
  left.addEventListener("mousedown", (e) => { e.preventDefault(); start = at(e); });
  left.addEventListener("mousemove", (e) => { if (start) drawn(e); });
  left.addEventListener("mouseup", (e) => {
    if (!start) return;
    $("obj-box").value = drawn(e).join(" ");
    start = null;
  });
  frame.append(left, box);
  $("obj-images").replaceChildren(frame, ...rest);
  $("obj-marks").tBodies[0].replaceChildren(...d.marks.map((m) => {
    const box = document.createElement("input");
    box.type = "checkbox";
    box.checked = true;
    box.dataset.id = String(m.id);
    return row([box, String(m.id), markKind(m), m.xyz_mm.map((v) => fmt(v, 1)).join(", "),
                fmt(m.size_mm ?? m.diameter_mm, 1)]);
  }));
}
// "Save" and "Teach the region" each start a new turn of the object step: a "Find marks" answer
// from an earlier turn (a slow one, arriving after "Save" was clicked) is dropped, so it never
// overwrites the later action's outcome or the marks it saved. Finds do not overtake each other:
// each answer is shown as it comes.
let objTurn = 0;
act("btn-obj-find", async () => {
  const turn = objTurn;
  const r = await call("POST", "/api/setup/object/find");
  if (turn !== objTurn) return;
  if (!r.ok) { $("obj-result").textContent = `${r.status}: ${r.data.message}`; return; }
  showMarks(r.data);
  $("obj-result").textContent = `${r.data.marks.length} mark(s) seen by both cameras: untick those not on the object` +
    (r.data.missed.length ? `; not found: ${r.data.missed.join("; ")}` : "");
});
act("btn-obj-template", async () => {
  const turn = ++objTurn;
  $("obj-template-result").textContent = "looking for the region in both images…";
  const r = await call("POST", "/api/setup/object/template",
                       { box: numbers($("obj-box").value), label: $("obj-label").value });
  if (turn !== objTurn) return;
  if (!r.ok) {
    $("obj-template-result").textContent = `REFUSED (${r.status}): ${r.data.message}`;
    $("obj-template-result").className = "status bad";
    return;
  }
  showMarks(r.data);
  const m = r.data.taught;
  $("obj-template-result").textContent = `TAUGHT: mark ${m.id}, template ${m.label}, ` +
    `${m.size_px} px (${fmt(m.size_mm, 1)} mm) at ${m.xyz_mm.map((v) => fmt(v, 1)).join(", ")} mm, ` +
    `score ${fmt(m.score, 2)}, epipolar ${fmt(m.epipolar_px, 2)} px`;
  $("obj-template-result").className = "status ok";
});
act("btn-obj-save", async () => {
  objTurn += 1;
  const marks = [...document.querySelectorAll("#obj-marks input:checked")].map((b) => Number(b.dataset.id));
  $("obj-result").textContent = "judging (as vgripd check does)…";
  const r = await call("POST", "/api/setup/object/save", { name: $("obj-name").value, marks });
  outcome($("obj-result"), r);
  const notes = (r.data.layout || []).map((f) => `${f.level}: ${f.message}`).join("; ");
  if (notes) $("obj-result").textContent += ` (${notes})`;
  load().catch(() => {});
});
async function trigger(el) {
  el.textContent = "job running…";
  const r = await call("POST", "/api/trigger");
  el.textContent = r.ok ? `test job: ${r.data.status} ${r.data.message || ""}` : `${r.status}: ${r.data.message}`;
  return r;
}
act("btn-teach-trigger", () => trigger($("teach-result")));
async function teach(url) {
  const r = await call("POST", url);
  const t = r.data;
  if ("applied" in t) outcome($("teach-result"), r);
  else if (t.shots) $("teach-result").textContent = `${t.refused ? `REFUSED: ${t.refused}; ` : ""}${t.shots.length} shot(s)` +
    (t.spread_mm === null ? "" : `, spread ${fmt(t.spread_mm, 3)} mm / ${fmt(t.spread_deg, 4)} deg`);
  else $("teach-result").textContent = `${r.status}: ${t.message}`;
}
act("btn-teach-shot", () => teach("/api/teach/shot"));
act("btn-teach-save", () => teach("/api/teach/save"));

// --- 5 link -----------------------------------------------------------------------------------
for (const b of ["abb", "fanuc", "kuka", "staubli", "ur", "yaskawa"]) {
  const o = document.createElement("option");
  o.value = b; o.textContent = b;
  $("link-brand").append(o);
}
act("btn-link-program", async () => {
  const resp = await fetch(`/api/setup/robot-program.zip?brand=${$("link-brand").value}`, { headers: headers(false) });
  if (!resp.ok) { $("link-result").textContent = `${resp.status}: ${await resp.text()}`; return; }
  const a = $("link-download");
  a.href = URL.createObjectURL(await resp.blob());
  a.download = `vgripd-${$("link-brand").value}.zip`;
  a.hidden = false;
  $("link-result").textContent = "program ready: save the zip; docs/robots/ says how to load it";
});

// --- 6 test pick ------------------------------------------------------------------------------
// --- choosing the cameras and the link (restart to run them) ---------------------------------
function restartNote(r) {
  const keys = (r.data.restart || []).join(", ");
  if (keys && r.ok) {
    $("restart-keys").textContent = keys;
    $("restart-result").textContent = "";
    $("restart-bar").hidden = false;
  }
  return keys ? ` Takes effect at the next start: ${keys}.` : "";
}
// The restart: judged by the server first; then the page waits for another daemon to answer.
act("btn-restart", async () => {
  const before = state.instance;
  $("restart-result").textContent = "judging the files as saved…";
  const r = await call("POST", "/api/setup/restart");
  if (!r.ok) { $("restart-result").textContent = `REFUSED (${r.status}): ${r.data.message}`; return; }
  $("restart-result").textContent = `RESTARTING: ${r.data.message}`;
  for (;;) {
    await new Promise((res) => setTimeout(res, 1000));
    const again = await call("GET", "/api/setup").catch(() => null);
    if (again && again.ok && again.data.instance !== before) break;
  }
  await load();
  $("restart-bar").hidden = true;
  $("setup-note").textContent = `RESTARTED: camera type ${state.camera.type}; links ${Object.keys(state.links || {}).join(", ")}`;
});
act("btn-cam-discover", async () => {
  $("cam-choose-result").textContent = "looking for cameras (vgripd cameras runs in a child process)…";
  const r = await call("GET", "/api/setup/cameras/discover");
  if (!r.ok) { $("cam-choose-result").textContent = `${r.status}: ${r.data.message}`; return; }
  const d = r.data;
  $("cam-type").replaceChildren(...d.types.map((t) => {
    const o = document.createElement("option"); o.value = t; o.textContent = t;
    o.selected = t === (d.devices.length ? d.devices[0].stack : d.current.type); return o;
  }));
  $("cam-devices").tBodies[0].replaceChildren(...d.devices.map((dev, i) => {
    const use = document.createElement("input"); use.type = "checkbox"; use.checked = i < 2;
    use.dataset.serial = dev.serial; use.dataset.stack = dev.stack;
    const name = document.createElement("input"); name.size = 10;
    name.value = d.devices.length === 2 ? ["left", "right"][i] : `cam${i}`;
    return row([use, dev.stack, dev.serial, `${dev.vendor} ${dev.model}`, dev.address || "", name]);
  }));
  const missing = Object.entries(d.unavailable || {}).map(([k, v]) => `${k}: ${v}`);
  $("cam-unavailable").textContent = (d.devices.length ? `${d.devices.length} device(s) found. ` :
    "No camera device found. ") + (missing.length ? `Not available: ${missing.join("; ")}` : "");
  $("cam-choose-result").textContent = `now: ${d.current.type}`;
});
act("btn-cam-choose", async () => {
  const kind = $("cam-type").value;
  const cameras = [...$("cam-devices").tBodies[0].rows]
    .filter((tr) => tr.cells[0].firstChild.checked && tr.cells[0].firstChild.dataset.stack === kind)
    .map((tr) => ({ name: tr.cells[5].firstChild.value, serial: tr.cells[0].firstChild.dataset.serial }));
  const body = { type: kind };
  if (cameras.length) body.cameras = cameras;
  const r = await call("POST", "/api/setup/cameras/choose", body);
  outcome($("cam-choose-result"), r);
  $("cam-choose-result").textContent += restartNote(r);
});
let linkDefaults = {};
async function linkOptions() {
  const r = await call("GET", "/api/setup/link/options");
  if (!r.ok) return;
  linkDefaults = Object.fromEntries(r.data.types.map((t) => [t.type, t.defaults]));
  const now = r.data.running.length ? r.data.running[0].type : r.data.types[0].type;
  $("link-type").replaceChildren(...r.data.types.map((t) => {
    const o = document.createElement("option"); o.value = t.type; o.textContent = `${t.type} (${t.kind})`;
    o.selected = t.type === now; return o;
  }));
  linkSettings();
}
function linkSettings() {
  const d = { ...(linkDefaults[$("link-type").value] || { type: $("link-type").value }) };
  delete d.example;
  $("link-settings").value = JSON.stringify(d, null, 2);
}
$("link-type").addEventListener("change", linkSettings);
act("btn-link-contract", async () => {
  const r = await call("GET", `/api/setup/link/contract?type=${encodeURIComponent($("link-type").value)}`);
  if (!r.ok) { $("link-contract").textContent = `${r.status}: ${r.data.message}`; return; }
  const d = r.data, parts = [`${d.type}: ${d.kind}`];
  if (d.registers) parts.push(`registers: see the table above (${d.map_doc})`);
  if (d.s7_udt) parts.push(`${d.s7_udt.command}\n${d.s7_udt.source}`);
  if (d.opcua) parts.push(`OPC UA nodes:\n${JSON.stringify(d.opcua, null, 2)}`);
  if (d.brands) parts.push(d.brands.length ? `robot programs: ${d.brands.join(", ")} (Download above)` :
    "the robot runs vgripd's URScript (docs/ur_rtde.md)");
  $("link-contract").textContent = parts.join("\n\n");
});
act("btn-link-choose", async () => {
  let link;
  try { link = JSON.parse($("link-settings").value); } catch (err) {
    $("link-choose-result").textContent = `settings: not JSON: ${err.message}`;
    $("link-choose-result").className = "status bad"; return;
  }
  const r = await call("POST", "/api/setup/link/choose", { links: [link] });
  outcome($("link-choose-result"), r);
  $("link-choose-result").textContent += restartNote(r);
});

function showJob(job) {
  $("pick-status").textContent = `job ${job.id} (${job.link}): ${job.status} ${job.message || ""}`;
  const t = job.target;
  const rows = t ? t.fields.map((f, i) => row([`${f} (${t.vendor})`, fmt(t.values[i], 3)])) : [];
  for (const [k, v] of Object.entries(job.residuals || {})) rows.push(row([k, fmt(v, 4)]));
  $("pick-values").tBodies[0].replaceChildren(...rows);
  if (job.images) $("pick-images").replaceChildren(img(`/api/jobs/${job.id}/image/left.jpg`, "left"));
}
act("btn-pick-trigger", async () => {
  const r = await trigger($("pick-status"));
  if (r.ok) {
    const jobs = await call("GET", "/api/jobs");
    if (jobs.ok && jobs.data.length) showJob(jobs.data[0]);
  }
});
const events = new EventSource("/api/events");
events.addEventListener("job", (e) => { if (step === "pick") showJob(JSON.parse(e.data)); });

// --- the check that ends each step ------------------------------------------------------------
async function check() {
  $("check-step").textContent = step;
  $("check-summary").textContent = "checking (vgripd check runs in a child process)…";
  const r = await call("GET", `/api/setup/check?step=${step}`);
  if (!r.ok) { $("check-summary").textContent = `${r.status}: ${r.data.message}`; return r; }
  $("check-summary").textContent = (r.data.ok ? "vgripd check: OK" : "vgripd check: ERRORS") +
    ` (${r.data.findings.length} finding(s) for this step, ${r.data.all} in all) ${r.data.summary}`;
  $("check-findings").replaceChildren(...r.data.findings.map((f) => li(`${f.level}: ${f.message}`, f.level.toLowerCase())));
  return r;
}
act("btn-check", check);
act("btn-done", async () => {
  await check();
  await call("POST", "/api/setup/done", { step, done: true });
  const ids = state.steps.map((s) => s.id);
  const next = ids[Math.min(ids.indexOf(step) + 1, ids.length - 1)];
  await load();
  if (next !== step) show(next, true);
});

load().then(() => {
  const open = state.steps.find((s) => !s.done);
  show(open ? open.id : "pick");
}).catch((err) => { $("setup-note").textContent = err.message; });
