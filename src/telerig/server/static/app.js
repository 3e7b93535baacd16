"use strict";
// The control center's pages: who is logged in, and the admin tables. Every state-changing
// request sends the session's CSRF token in X-CSRF-Token.
let csrf = "";

async function api(path, options = {}) {
  const headers = { ...(options.headers || {}) };
  if (options.method && options.method !== "GET") headers["X-CSRF-Token"] = csrf;
  const reply = await fetch(path, { ...options, headers });
  if (reply.status === 401) {
    window.location.assign("/login");
    throw new Error("logged out");
  }
  return reply;
}

function row(table, cells) {
  const tr = document.createElement("tr");
  for (const value of cells) {
    const td = document.createElement("td");
    td.textContent = value;  // never innerHTML: names and details come from users
    tr.appendChild(td);
  }
  document.querySelector(`#${table} tbody`).appendChild(tr);
}

async function start() {
  const me = await (await api("/api/me")).json();
  csrf = me.csrf;
  document.getElementById("who").textContent = `${me.user} (${me.role})`;
  document.getElementById("logout").addEventListener("click", async () => {
    await api("/api/logout", { method: "POST" });
    window.location.assign("/login");
  });
  if (me.role !== "admin") return;
  document.getElementById("admin").hidden = false;
  for (const u of await (await api("/api/users")).json()) {
    row("users", [u.name, u.role, u.disabled ? "disabled" : "active"]);
  }
  for (const e of await (await api("/api/audit?limit=50")).json()) {
    row("audit", [new Date(e.t_ns / 1e6).toLocaleString(), e.user || "-", e.action, e.target, e.client]);
  }
}

start();
