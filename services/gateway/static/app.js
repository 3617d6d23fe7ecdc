// The ground-station page: start a task, follow its SSE stream, poll the camera and the vehicle state.
"use strict";

const API = "/api/v1";
const $ = (id) => document.getElementById(id);
const state = { task: null, lastEventId: 0, streaming: false, trail: [], vehicle: null, camUrl: null,
                steps: new Map() };

$("token").value = sessionStorage.getItem("aermani.token") || "";
$("token").addEventListener("input", () => sessionStorage.setItem("aermani.token", $("token").value));

function authHeaders(extra = {}) {
  const t = $("token").value.trim();
  return t ? { ...extra, Authorization: `Bearer ${t}` } : extra;
}

function say(text, isError = false) {
  const m = $("message");
  m.textContent = text;
  m.className = isError ? "err" : "muted";
}

async function api(method, path, body) {
  // Every state-changing request is JSON (the gateway refuses anything else: no cross-site form posts).
  const changes = method !== "GET";
  const opts = { method, headers: authHeaders(changes ? { "Content-Type": "application/json" } : {}) };
  if (changes) opts.body = JSON.stringify(body ?? {});
  const r = await fetch(API + path, opts);
  const data = r.headers.get("content-type")?.includes("json") ? await r.json() : null;
  if (!r.ok) throw new Error(data?.detail || `${r.status} ${r.statusText}`);
  return data;
}

// ---- task start and abort

$("task-form").addEventListener("submit", async (ev) => {
  ev.preventDefault();
  try {
    const body = { command: $("command").value };
    if (state.vehicle) body.vehicle_id = state.vehicle;
    const created = await api("POST", "/tasks", body);
    follow(created.task_id);
    say(`task ${created.task_id} accepted on ${created.vehicle_id}`);
  } catch (e) { say(e.message, true); }
});

$("abort").addEventListener("click", async () => {
  try {
    let out;
    if (state.task && !isTerminal($("task-state").textContent)) {
      try { out = await api("POST", `/tasks/${state.task}/abort`, { reason: "abort button" }); }
      catch (e) { out = null; }
    }
    if (!out) out = await api("POST", "/abort", { reason: "abort button" });
    say(`abort sent to ${out.vehicles.join(", ")}; acknowledged by ${out.acknowledged.join(", ") || "nobody yet"}`);
  } catch (e) { say(`abort failed: ${e.message}`, true); }
});

$("abort-all").addEventListener("click", async () => {
  try {
    const out = await api("POST", "/abort", { reason: "abort-all button" });
    say(`fleet abort sent (${out.vehicles.length} vehicles); acknowledged by ${out.acknowledged.join(", ") || "nobody yet"}`);
  } catch (e) { say(`abort failed: ${e.message}`, true); }
});

const isTerminal = (s) => ["succeeded", "failed", "aborted", "timeout"].includes(s);

// ---- the event stream (fetch, not EventSource: EventSource cannot send the Authorization header)

function follow(taskId) {
  state.task = taskId;
  state.lastEventId = 0;
  state.steps.clear();
  $("timeline").innerHTML = "";
  $("task-id").textContent = taskId;
  $("task-state").textContent = "pending";
  $("current-skill").textContent = "–";
  stream(taskId);
}

async function stream(taskId) {
  let retry = 500;
  while (state.task === taskId) {
    try {
      const headers = authHeaders(state.lastEventId ? { "Last-Event-ID": String(state.lastEventId) } : {});
      const r = await fetch(`${API}/tasks/${taskId}/events`, { headers });
      if (!r.ok) { const d = await r.json().catch(() => ({})); throw new Error(d.detail || r.statusText); }
      const reader = r.body.pipeThrough(new TextDecoderStream()).getReader();
      let buf = "";
      for (;;) {
        const { value, done } = await reader.read();
        if (done) break;
        buf += value;
        let cut;
        while ((cut = buf.indexOf("\n\n")) >= 0 || (cut = buf.indexOf("\r\n\r\n")) >= 0) {
          const block = buf.slice(0, cut);
          buf = buf.slice(cut + (buf.startsWith("\r\n\r\n", cut) ? 4 : 2));
          handleBlock(taskId, block);
        }
      }
      if (isTerminal($("task-state").textContent)) return;
    } catch (e) {
      say(`event stream: ${e.message}; retrying`, true);
    }
    await new Promise((res) => setTimeout(res, retry));
    retry = Math.min(retry * 2, 5000);
  }
}

function handleBlock(taskId, block) {
  const ev = { event: "message", data: "" };
  for (const line of block.split(/\r?\n/)) {
    if (!line || line.startsWith(":")) continue;
    const i = line.indexOf(":");
    const field = i < 0 ? line : line.slice(0, i);
    const value = i < 0 ? "" : line.slice(i + 1).replace(/^ /, "");
    if (field === "data") ev.data += (ev.data ? "\n" : "") + value; else ev[field] = value;
  }
  if (!ev.data || state.task !== taskId) return;
  if (ev.id) state.lastEventId = Number(ev.id);
  const data = JSON.parse(ev.data);
  if (ev.event === "step") renderStep(data);
  else if (ev.event === "skill_status") {
    $("current-skill").textContent = `${data.skill}${data.argument ? "(" + data.argument + ")" : ""} – ${data.state}`;
  } else if (ev.event === "task_status") {
    $("task-state").textContent = data.state;
    if (data.message) say(`${data.state}: ${data.message}`, data.state !== "succeeded" && isTerminal(data.state));
  }
}

function el(tag, attrs = {}, ...children) {
  const e = document.createElement(tag);
  Object.assign(e, attrs);
  for (const c of children) if (c != null) e.append(c);
  return e;
}

function renderStep(s) {
  const ste = s.ste ? `${s.ste.skill}${s.ste.argument ? "(" + s.ste.argument + ")" : ""}` : "no valid answer";
  const li = el("li", { className: `step ${s.skill_state || ""}` });
  li.dataset.step = s.step;
  li.append(el("div", {}, el("span", { className: "ste", textContent: `#${s.step} ${ste}` }),
               el("span", { className: "muted", textContent: ` ${s.skill_state || ""} ${s.skill_message || ""}` })));
  const drt = s.drt || {};
  const dl = el("dl");
  for (const [name, value] of [["image description", drt.image_description], ["summary", drt.summary],
                               ["reasoning", drt.reasoning]]) {
    if (value) dl.append(el("dt", { textContent: name }), el("dd", { className: name.replace(" ", "-"),
                                                                     textContent: value }));
  }
  li.append(dl);
  if (drt.action_predictions) {
    const d = el("details", {}, el("summary", { textContent: "action predictions" }));
    const pl = el("dl");
    for (const [k, v] of Object.entries(drt.action_predictions)) pl.append(el("dt", { textContent: k }),
                                                                           el("dd", { textContent: v }));
    d.append(pl);
    li.append(d);
  }
  const calls = s.calls || [];
  const invalid = calls.filter((c) => !c.valid).length;
  li.append(el("div", { className: "muted", textContent:
    `${calls.length} model call(s), ${invalid} invalid, ${calls.map((c) => c.latency_s.toFixed(2) + " s").join(", ")}` }));
  const old = state.steps.get(s.step);
  if (old) old.replaceWith(li); else $("timeline").append(li);
  state.steps.set(s.step, li);
  li.scrollIntoView({ block: "nearest" });
}

// ---- fleet health, pose and map

async function pollHealth() {
  try {
    const h = await api("GET", "/health");
    const sel = $("vehicle");
    const ids = h.vehicles.filter((v) => v.services.reasoner).map((v) => v.vehicle_id);
    if ([...sel.options].map((o) => o.value).join() !== ids.join()) {
      sel.innerHTML = "";
      for (const id of ids) sel.append(el("option", { value: id, textContent: id }));
    }
    state.vehicle = sel.value || null;
    const v = h.vehicles.find((x) => x.vehicle_id === state.vehicle);
    if (v) {
      const down = Object.entries(v.services).filter(([, up]) => !up).map(([n]) => n);
      $("health").textContent = `link ${v.link_ok ? "ok" : "LOST"} · offboard ${v.offboard_ok ? "on" : "off"} · ` +
        `battery ${v.battery_remaining == null ? "?" : v.battery_remaining.toFixed(0) + "%"}` +
        ` · perception ${v.segmenter || "?"}${v.segmenter === "sim" ? " (ground-truth oracle)" : ""}` +
        (v.realism ? ` · sim ${v.realism}` : "") +
        (down.length ? ` · down: ${down.join(", ")}` : "");
      if (v.state) updatePose(v.state);
      if (!state.task && v.running_task) follow(v.running_task);
    } else $("health").textContent = "no vehicle with a reasoner";
  } catch (e) { $("health").textContent = `gateway unreachable: ${e.message}`; }
  setTimeout(pollHealth, 500);
}

function updatePose(s) {
  const p = s.position;
  const last = state.trail[state.trail.length - 1];
  if (!last || Math.hypot(p.x - last.x, p.y - last.y) > 0.02) state.trail.push({ x: p.x, y: p.y });
  if (state.trail.length > 2000) state.trail.shift();
  $("pose").textContent = `x ${p.x.toFixed(2)}  y ${p.y.toFixed(2)}  z ${p.z.toFixed(2)} m  ` +
    `yaw ${(s.yaw * 180 / Math.PI).toFixed(0)}°  ${s.mode}${s.armed ? " armed" : ""}  gripper ${s.gripper}`;
  drawMap(p, s.yaw);
}

function drawMap(p, yaw) {
  const c = $("map"), g = c.getContext("2d");
  const pts = [...state.trail, p];
  const span = Math.max(4, ...pts.map((q) => Math.max(Math.abs(q.x - p.x), Math.abs(q.y - p.y)) * 2.4));
  const scale = c.width / span;
  // World ENU to canvas: x to the right, y up, centred on the vehicle.
  const tx = (x) => c.width / 2 + (x - p.x) * scale, ty = (y) => c.height / 2 - (y - p.y) * scale;
  g.clearRect(0, 0, c.width, c.height);
  g.strokeStyle = "#2a2a2a";
  g.lineWidth = 1;
  for (let k = Math.floor(p.x - span); k <= p.x + span; k++) { g.beginPath(); g.moveTo(tx(k), 0); g.lineTo(tx(k), c.height); g.stroke(); }
  for (let k = Math.floor(p.y - span); k <= p.y + span; k++) { g.beginPath(); g.moveTo(0, ty(k)); g.lineTo(c.width, ty(k)); g.stroke(); }
  g.strokeStyle = "#4da3ff";
  g.lineWidth = 2;
  g.beginPath();
  state.trail.forEach((q, i) => (i ? g.lineTo(tx(q.x), ty(q.y)) : g.moveTo(tx(q.x), ty(q.y))));
  g.stroke();
  g.save();
  g.translate(tx(p.x), ty(p.y));
  g.rotate(-yaw);
  g.fillStyle = "#ffb000";
  g.beginPath(); g.moveTo(12, 0); g.lineTo(-8, 7); g.lineTo(-8, -7); g.closePath(); g.fill();
  g.restore();
}

// ---- camera (polled with the token; an <img src> cannot carry the Authorization header)

async function pollCamera() {
  if (state.vehicle) {
    try {
      const r = await fetch(`${API}/vehicles/${state.vehicle}/camera.jpg`, { headers: authHeaders() });
      if (r.ok) {
        const url = URL.createObjectURL(await r.blob());
        const img = $("camera");
        img.src = url;
        img.dataset.stamp = r.headers.get("X-Frame-Stamp-Ns") || "";
        if (state.camUrl) URL.revokeObjectURL(state.camUrl);
        state.camUrl = url;
      }
    } catch (e) { /* the next poll retries */ }
  }
  setTimeout(pollCamera, 250);
}

// ---- operator approvals: skills the policy chose that wait for Approve or Reject

async function decide(id, approve) {
  const reason = approve ? "" : (prompt("Why reject? (the policy reads this)") || "rejected by the operator");
  try {
    await api("POST", `/approvals/${id}`, { approve, reason, operator: "web page" });
    say(`${approve ? "approved" : "rejected"} ${id}`);
  } catch (e) { say(`decision failed: ${e.message}`, true); }
  pollApprovals(false);
}

async function pollApprovals(again = true) {
  try {
    const pending = await api("GET", "/approvals");
    const list = $("approval-list");
    list.innerHTML = "";
    for (const a of pending) {
      const call = a.argument ? `${a.skill}(${a.argument})` : a.skill;
      const left = a.expires_ns ? Math.max(0, Math.round((a.expires_ns / 1e6 - Date.now()) / 1000)) : null;
      const approve = el("button", { className: "approve", type: "button", textContent: "Approve" });
      const reject = el("button", { className: "reject", type: "button", textContent: "Reject" });
      approve.addEventListener("click", () => decide(a.approval_id, true));
      reject.addEventListener("click", () => decide(a.approval_id, false));
      const item = el("li", { className: "approval" },
        el("strong", { textContent: `${a.vehicle_id} step ${a.step}: ${call}` }),
        el("div", { className: "muted", textContent: a.reasoning || "" }),
        el("div", { className: "muted", textContent: left == null ? "" : `holds and fails the step in ${left} s` }),
        approve, reject);
      item.dataset.id = a.approval_id;
      list.append(item);
    }
    $("approvals").hidden = pending.length === 0;
  } catch (e) { /* no token yet, or the gateway restarts: the next poll retries */ }
  if (again) setTimeout(pollApprovals, 700);
}

pollHealth();
pollCamera();
pollApprovals();
