"use strict";
// Segment review: the videos with segments, one video with its segments as coloured bars on a
// timeline, and a reviewer's keys (j/k select, space play the segment, a accept, r reject, e rename,
// [ ] set start/end to the playhead, n new segment, u undo). Every edit names the version it was
// made against; a stale one is refused (409) and the page reloads the segments. Data from the
// server is shown with textContent only; every POST sends X-CSRF-Token.
let role = "viewer";
let item = null;       // the ReviewDetail on screen
let selectedId = null; // the selected segment's id
let stopAt = null;     // playing one segment: pause here [s]
let naming = null;     // the inline input's purpose: "rename" | "add"

const $ = (id) => document.getElementById(id);

function showError(err) {
  $("error").textContent = err ? String(err.message || err) : "";
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

const fmt = (x) => Number(x).toFixed(2);

async function loadItems() {
  const rows = await (await apiOk("/api/review")).json();
  const body = document.querySelector("#items tbody");
  clear(body);
  for (const r of rows) {
    const tr = document.createElement("tr");
    tr.className = "clickable";
    tr.dataset.id = r.id;
    for (const v of [r.id, r.title, fmt(r.duration_s), r.segments, r.proposed, r.accepted, r.corrected, r.rejected]) cell(tr, v);
    tr.addEventListener("click", () => openItem(r.id));
    body.appendChild(tr);
  }
}

async function openItem(id) {
  showError(null);
  let d;
  try {
    d = await (await apiOk(`/api/review/${encodeURIComponent(id)}`)).json();
  } catch (err) {
    showError(err);
    return;
  }
  const fresh = !item || item.id !== d.id;
  item = d;
  $("reviewer").hidden = false;
  $("title").textContent = d.title;
  if (fresh) {
    $("video").src = `/api/review/${encodeURIComponent(d.id)}/video`;
    selectedId = d.segments.length ? d.segments[0].id : null;
    const url = new URL(window.location.href);
    url.searchParams.set("item", d.id);
    window.history.replaceState(null, "", url);
  }
  render();
}

function selected() {
  return item ? item.segments.find((s) => s.id === selectedId) || null : null;
}

function render() {
  if (!item) return;
  if (!selected() && item.segments.length) selectedId = item.segments[0].id;
  const line = $("timeline");
  for (const el of Array.from(line.querySelectorAll(".seg"))) el.remove();
  const total = Math.max(item.duration_s, 0.01);
  const body = document.querySelector("#segments tbody");
  clear(body);
  item.segments.forEach((s, i) => {
    const bar = document.createElement("div");
    bar.className = "seg" + (s.id === selectedId ? " selected" : "");
    bar.dataset.status = s.status;
    bar.dataset.id = s.id;
    bar.style.left = `${(100 * s.start_s) / total}%`;
    bar.style.width = `${Math.max(0.3, (100 * (s.end_s - s.start_s)) / total)}%`;
    bar.textContent = s.label;
    bar.title = `${s.label} ${fmt(s.start_s)}-${fmt(s.end_s)} s (${s.status})`;
    line.appendChild(bar);
    const tr = document.createElement("tr");
    tr.className = "clickable" + (s.id === selectedId ? " selected" : "");
    tr.dataset.id = s.id;
    tr.dataset.status = s.status;
    for (const v of [i + 1, s.label, fmt(s.start_s), fmt(s.end_s), s.status, s.source, fmt(s.confidence)]) cell(tr, v);
    tr.addEventListener("click", () => select(s.id, true));
    body.appendChild(tr);
  });
  const s = selected();
  $("selected").textContent = s
    ? `${item.segments.indexOf(s) + 1}/${item.segments.length}: ${s.label} · ${fmt(s.start_s)}-${fmt(s.end_s)} s · ${s.status} · ${s.source}`
    : item.empty ? "no action found in this video (n draws one)" : "";
  $("annotation").textContent = s && s.annotation ? s.annotation : "";
  $("version").textContent = `version ${item.version}`;
  document.body.dataset.version = item.version;
  playhead();
}

function playhead() {
  if (!item) return;
  const v = $("video");
  $("playhead").style.left = `${(100 * (v.currentTime || 0)) / Math.max(item.duration_s, 0.01)}%`;
}

function select(id, seek) {
  selectedId = id;
  stopAt = null;
  const s = selected();
  if (s && seek) $("video").currentTime = s.start_s;
  render();
}

function step(delta) {
  if (!item || !item.segments.length) return;
  const i = item.segments.findIndex((s) => s.id === selectedId);
  const next = Math.min(item.segments.length - 1, Math.max(0, (i < 0 ? 0 : i) + delta));
  select(item.segments[next].id, true);
}

function playSegment() {
  const v = $("video");
  const s = selected();
  if (!v.paused) {
    v.pause();
    stopAt = null;
    return;
  }
  if (s) {
    v.currentTime = s.start_s;
    stopAt = s.end_s;
  }
  v.play().catch((err) => showError(err));
}

async function edit(body) {
  if (!item) return;
  if (role === "viewer") {
    showError("reviewing needs the operator role");
    return;
  }
  showError(null);
  try {
    const d = await (await apiOk(`/api/review/${encodeURIComponent(item.id)}/edits`, {
      method: "POST",
      body: JSON.stringify({ ...body, version: item.version }),
    })).json();
    item = d;
    if (body.op === "add") {
      const mine = d.segments.find((s) => s.label === body.label && fmt(s.start_s) === fmt(body.start_s));
      if (mine) selectedId = mine.id;
    }
    render();
    loadItems().catch(() => {});
  } catch (err) {
    showError(err);
    if (err.status === 409) openItem(item.id);  // someone else edited: show what is there now
  }
}

const now = () => Math.round(($("video").currentTime || 0) * 100) / 100;

function startNaming(mode) {
  const s = selected();
  if (mode === "rename" && !s) return;
  naming = mode;
  const input = $("rename");
  input.value = mode === "rename" ? s.label : "";
  input.placeholder = mode === "rename" ? "new label" : "label of the new segment";
  input.hidden = false;
  input.focus();
  input.select();
}

function endNaming(save) {
  const input = $("rename");
  const label = input.value.trim();
  const mode = naming;
  naming = null;
  input.hidden = true;
  $("timeline").focus();
  if (!save || !label) return;
  const s = selected();
  if (mode === "rename" && s) {
    edit({ op: "rename", segment_id: s.id, label });
  } else if (mode === "add") {
    const start = now();
    const end = Math.min(item.duration_s, Math.round((start + 1) * 100) / 100);
    edit({ op: "add", label, start_s: start, end_s: end > start ? end : item.duration_s });
  }
}

function onKey(ev) {
  if (!item || ev.ctrlKey || ev.metaKey || ev.altKey) return;
  if (ev.target === $("rename")) {
    if (ev.key === "Enter") { ev.preventDefault(); endNaming(true); }
    if (ev.key === "Escape") { ev.preventDefault(); endNaming(false); }
    return;
  }
  const s = selected();
  const keys = {
    j: () => step(1),
    k: () => step(-1),
    " ": playSegment,
    a: () => s && edit({ op: "accept", segment_id: s.id }),
    r: () => s && edit({ op: "reject", segment_id: s.id }),
    e: () => startNaming("rename"),
    "[": () => s && edit({ op: "bounds", segment_id: s.id, start_s: now() }),
    "]": () => s && edit({ op: "bounds", segment_id: s.id, end_s: now() }),
    n: () => startNaming("add"),
    u: () => edit({ op: "undo" }),
  };
  const action = keys[ev.key];
  if (!action) return;
  ev.preventDefault();  // space must not also toggle the video or scroll the page
  ev.stopPropagation();
  action();
}

async function start() {
  const me = await (await apiOk("/api/me")).json();
  csrf = me.csrf;
  role = me.role;
  $("who").textContent = `${me.user} (${me.role})`;
  $("logout").addEventListener("click", async () => {
    await apiOk("/api/logout", { method: "POST" });
    window.location.assign("/login");
  });
  const video = $("video");
  video.addEventListener("timeupdate", () => {
    if (stopAt !== null && video.currentTime >= stopAt) {
      video.pause();
      stopAt = null;
    }
    playhead();
  });
  video.addEventListener("seeked", playhead);
  $("timeline").addEventListener("click", (ev) => {
    if (!item) return;
    const box = $("timeline").getBoundingClientRect();
    const t = Math.max(0, Math.min(item.duration_s, ((ev.clientX - box.left) / box.width) * item.duration_s));
    const bar = ev.target.closest ? ev.target.closest(".seg") : null;
    if (bar) selectedId = bar.dataset.id;
    video.currentTime = t;
    render();
  });
  $("rename").addEventListener("blur", () => { if (naming) endNaming(false); });
  window.addEventListener("keydown", onKey, true);
  await loadItems();
  const wanted = new URL(window.location.href).searchParams.get("item");
  if (wanted) await openItem(wanted);
  document.body.dataset.ready = "1";
}

start().catch(showError);
