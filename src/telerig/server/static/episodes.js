"use strict";
// The episode browser: filters, the episode table, an episode's videos, plot and gate verdicts,
// labels, the failures partition, and the jobs (export, quality check) with their progress.
// Data from the server is shown with textContent only; every POST sends X-CSRF-Token.
let role = "viewer";
let offset = 0;
const LIMIT = 50;
let current = null;

function showError(err) {
  document.getElementById("error").textContent = err ? String(err.message || err) : "";
}

function cell(tr, value) {
  const td = document.createElement("td");
  td.textContent = value;
  tr.appendChild(td);
  return td;
}

function clear(el) {
  while (el.firstChild) el.removeChild(el.firstChild);
}

function date(ns) {
  return new Date(ns / 1e6).toISOString().replace("T", " ").slice(0, 19);
}

function num(value, digits) {
  return value === null || value === undefined ? "-" : Number(value).toFixed(digits);
}

function query() {
  const form = new FormData(document.getElementById("filters"));
  const params = new URLSearchParams();
  for (const [key, value] of form.entries()) {
    if (value === "") continue;
    if (key === "since" || key === "until") {
      const day = new Date(`${value}T00:00:00Z`);
      if (key === "until") day.setUTCDate(day.getUTCDate() + 1);  // a whole day
      params.set(key, day.toISOString());
    } else {
      params.set(key, value);
    }
  }
  params.set("limit", LIMIT);
  params.set("offset", offset);
  return params;
}

async function loadList() {
  showError(null);
  let page;
  try {
    page = await (await apiOk(`/api/episodes?${query()}`)).json();
  } catch (err) {
    showError(err);
    return;
  }
  const body = document.querySelector("#episodes tbody");
  clear(body);
  for (const e of page.episodes) {
    const tr = document.createElement("tr");
    tr.className = "clickable";
    cell(tr, e.id);
    cell(tr, date(e.start_ns));
    cell(tr, e.task);
    cell(tr, e.operator);
    cell(tr, e.robots.join(", ") || "-");
    cell(tr, num(e.duration_s, 1));
    cell(tr, num(e.quality, 2));
    cell(tr, e.status);
    cell(tr, !e.gates_checked ? "-" : e.gates_failed.length ? `failed: ${e.gates_failed.join(", ")}` : "passed");
    cell(tr, e.outcome || "-");
    tr.addEventListener("click", () => loadDetail(e.id));
    body.appendChild(tr);
  }
  const last = Math.min(page.offset + page.episodes.length, page.total);
  document.getElementById("range").textContent = page.total ? `${page.offset + 1}–${last} of ${page.total}` : "no episodes";
  document.getElementById("prev").disabled = page.offset === 0;
  document.getElementById("next").disabled = last >= page.total;
}

async function loadDetail(id) {
  showError(null);
  let d;
  try {
    d = await (await apiOk(`/api/episodes/${encodeURIComponent(id)}`)).json();
  } catch (err) {
    showError(err);
    return;
  }
  current = d;
  document.getElementById("detail").hidden = false;
  document.getElementById("detail-title").textContent = `${d.id} · ${d.task}`;
  const label = d.label ? ` (labelled by ${d.label.by})` : "";
  document.getElementById("detail-meta").textContent =
    `${date(d.start_ns)} UTC · ${num(d.duration_s, 1)} s · ${d.operator} · rig ${d.rig} · ` +
    `${d.status} in ${d.partition}/ · outcome ${d.outcome || "-"}${label}`;
  document.getElementById("move").textContent = d.partition === "failures" ? "Restore from failures" : "Move to failures";
  const reasons = document.getElementById("failure-reasons");
  clear(reasons);
  for (const r of d.failure_reasons) {
    const li = document.createElement("li");
    li.textContent = r;
    reasons.appendChild(li);
  }
  document.getElementById("review-link").href = `/review?item=${encodeURIComponent(d.id)}`;
  const videos = document.getElementById("videos");
  clear(videos);
  for (const c of d.cameras) {
    const figure = document.createElement("figure");
    const video = document.createElement("video");
    video.controls = true;
    video.preload = "metadata";
    video.src = `/api/episodes/${encodeURIComponent(d.id)}/video/${encodeURIComponent(c.name)}`;
    const caption = document.createElement("figcaption");
    caption.textContent = `${c.name}: ${c.width || "?"}x${c.height || "?"} @ ${c.fps || "?"} Hz, ${c.frames} frames, ${c.dropped} dropped`;
    figure.appendChild(video);
    figure.appendChild(caption);
    videos.appendChild(figure);
  }
  document.getElementById("score").textContent = d.score === null ? "" : `· score ${num(d.score, 2)}`;
  const gates = document.querySelector("#gates tbody");
  clear(gates);
  for (const g of d.gates) {
    const tr = document.createElement("tr");
    cell(tr, g.gate);
    const result = cell(tr, g.passed === null ? "n/a" : g.passed ? "passed" : "FAILED");
    if (g.passed === false) result.className = "bad";
    cell(tr, g.value === null ? "-" : `${num(g.value, 3)} ${g.unit}`);
    cell(tr, g.threshold === null ? "-" : `${num(g.threshold, 3)} ${g.unit}`);
    cell(tr, g.detail);
    gates.appendChild(tr);
  }
  const plot = document.getElementById("plot");
  const status = document.getElementById("plot-status");
  plot.hidden = true;
  status.textContent = "rendering…";
  plot.onload = () => { plot.hidden = false; status.textContent = ""; };
  plot.onerror = () => { status.textContent = "no plot for this episode"; };
  plot.src = `/api/episodes/${encodeURIComponent(d.id)}/plot.png`;
  document.getElementById("detail").scrollIntoView({ behavior: "smooth" });
}

async function act(path, body) {
  showError(null);
  try {
    await apiOk(path, { method: "POST", body: body === undefined ? undefined : JSON.stringify(body) });
  } catch (err) {
    showError(err);
    return false;
  }
  return true;
}

async function label(outcome) {
  if (!current) return;
  if (await act(`/api/episodes/${encodeURIComponent(current.id)}/label`, { outcome })) {
    await loadDetail(current.id);
    await loadList();
  }
}

async function move() {
  if (!current) return;
  const where = current.partition === "failures" ? "restore" : "failures";
  if (await act(`/api/episodes/${encodeURIComponent(current.id)}/${where}`)) {
    await loadDetail(current.id);
    await loadList();
  }
}

async function startJob(kind) {
  if (!current) return;
  let params;
  if (kind === "export") {
    const name = window.prompt("Dataset name (under exports/; an existing one is appended to)", "lerobot-" + current.task.replace(/[^A-Za-z0-9_.-]+/g, "_").slice(0, 40));
    if (!name) return;
    params = { format: "lerobot", name, ids: [current.id], include_failures: current.partition === "failures" };
  } else {
    params = { ids: [current.id] };
  }
  if (await act("/api/jobs", { kind, params })) await loadJobs();
}

async function loadJobs() {
  let jobs;
  try {
    jobs = await (await apiOk("/api/jobs?limit=20")).json();
  } catch (_) {
    return;
  }
  const body = document.querySelector("#jobs tbody");
  clear(body);
  for (const j of jobs) {
    const tr = document.createElement("tr");
    cell(tr, String(j.id));
    cell(tr, j.kind === "export" ? `export ${j.params.format} → ${j.params.name}` : "quality check");
    cell(tr, j.user);
    const state = cell(tr, j.state);
    if (j.state === "failed") state.className = "bad";
    const progress = document.createElement("progress");
    progress.max = Math.max(j.total, 1);
    progress.value = j.state === "done" ? progress.max : j.done;
    const td = document.createElement("td");
    td.appendChild(progress);
    tr.appendChild(td);
    cell(tr, j.error || j.message);
    body.appendChild(tr);
  }
}

async function start() {
  const me = await (await apiOk("/api/me")).json();
  csrf = me.csrf;
  role = me.role;
  document.getElementById("who").textContent = `${me.user} (${me.role})`;
  document.getElementById("logout").addEventListener("click", async () => {
    await apiOk("/api/logout", { method: "POST" });
    window.location.assign("/login");
  });
  for (const el of document.querySelectorAll(".operator-only")) el.hidden = role === "viewer";
  document.getElementById("filters").addEventListener("submit", (ev) => {
    ev.preventDefault();
    offset = 0;
    loadList();
  });
  document.getElementById("prev").addEventListener("click", () => { offset = Math.max(0, offset - LIMIT); loadList(); });
  document.getElementById("next").addEventListener("click", () => { offset += LIMIT; loadList(); });
  document.getElementById("label-success").addEventListener("click", () => label("success"));
  document.getElementById("label-failure").addEventListener("click", () => label("failure"));
  document.getElementById("move").addEventListener("click", move);
  document.getElementById("export").addEventListener("click", () => startJob("export"));
  document.getElementById("qa").addEventListener("click", () => startJob("qa"));
  await loadList();
  await loadJobs();
  setInterval(loadJobs, 1500);  // jobs started anywhere show here, with their progress
  const wanted = new URLSearchParams(window.location.search).get("id");
  if (wanted) loadDetail(wanted);
}

start().catch((err) => {
  if (err.message !== LOGGED_OUT) showError(err);  // a 401 already went to the login page
});
