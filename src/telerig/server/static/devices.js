"use strict";
// The devices admin page: registered devices, register (admin) with a one-time password dialog,
// revoke. Text goes in with textContent only; every POST/DELETE sends the CSRF token.
let rigs = [];

function showError(text) {
  document.getElementById("error").textContent = text;
}

function cell(tr, value) {
  const td = document.createElement("td");
  td.textContent = value;
  tr.appendChild(td);
  return td;
}

async function refresh(admin) {
  const reply = await api("/api/devices");
  if (!reply.ok) {
    showError(await problem(reply));
    return;
  }
  const body = document.querySelector("#devices tbody");
  body.replaceChildren();
  for (const d of await reply.json()) {
    const tr = document.createElement("tr");
    cell(tr, d.rig);
    cell(tr, d.principal);
    cell(tr, d.kind);
    cell(tr, d.device);
    cell(tr, new Date(d.created_ns / 1e6).toLocaleString());
    cell(tr, d.created_by);
    cell(tr, d.active ? "active" : `revoked by ${d.revoked_by}`);
    cell(tr, d.publishes.join(" "));
    const actions = cell(tr, "");
    if (admin && d.active) {
      const button = document.createElement("button");
      button.type = "button";
      button.textContent = "Revoke";
      button.addEventListener("click", () => revoke(d));
      actions.appendChild(button);
    }
    body.appendChild(tr);
  }
}

async function revoke(d) {
  if (!window.confirm(`Revoke ${d.principal} on ${d.rig}? It is disconnected from the broker.`)) return;
  const reply = await api(`/api/devices/${encodeURIComponent(d.rig)}/${encodeURIComponent(d.principal)}`, {
    method: "DELETE",
  });
  showError(reply.ok ? "" : await problem(reply));
  if (reply.ok) {
    const r = await reply.json();
    if (r.broker.status !== "signalled") showError(r.broker.detail);
  }
  await refresh(true);
}

function fillDevices() {
  const rig = rigs.find((r) => r.rig === document.getElementById("rig").value);
  const kind = document.getElementById("kind").value;
  const select = document.getElementById("device");
  select.replaceChildren();
  for (const id of rig ? rig[kind] : []) {
    const option = document.createElement("option");
    option.value = id;
    option.textContent = id;
    select.appendChild(option);
  }
}

async function register(event) {
  event.preventDefault();
  showError("");
  const form = new FormData(event.target);
  const reply = await api("/api/devices", {
    method: "POST",
    body: JSON.stringify({ rig: form.get("rig"), kind: form.get("kind"), device: form.get("device") }),
  });
  if (!reply.ok) {
    showError(await problem(reply));
    return;
  }
  const issued = await reply.json();
  document.getElementById("issued-user").textContent = `${issued.device.device} (${issued.device.rig})`;
  document.getElementById("issued-username").textContent = issued.username;
  document.getElementById("issued-password").textContent = issued.password;
  document.getElementById("issued-broker").textContent = issued.broker.detail;
  document.getElementById("issued").showModal();
  await refresh(true);
}

async function start() {
  const me = await (await api("/api/me")).json();
  csrf = me.csrf;
  document.getElementById("who").textContent = `${me.user} (${me.role})`;
  const admin = me.role === "admin";
  const dialog = document.getElementById("issued");
  // The password is gone from the page once the dialog closes: at once on Close (the dialog's
  // "close" event comes a task later), and on the event for any other way out (Esc).
  const forget = () => {
    document.getElementById("issued-password").textContent = "";
  };
  document.getElementById("issued-close").addEventListener("click", () => {
    forget();
    dialog.close();
  });
  dialog.addEventListener("close", forget);
  if (admin) {
    const reply = await api("/api/devices/rigs");
    if (reply.ok) {
      rigs = await reply.json();
      const select = document.getElementById("rig");
      for (const r of rigs) {
        const option = document.createElement("option");
        option.value = r.rig;
        option.textContent = r.rig;
        select.appendChild(option);
      }
      select.addEventListener("change", fillDevices);
      document.getElementById("kind").addEventListener("change", fillDevices);
      fillDevices();
      document.getElementById("register").addEventListener("submit", register);
      document.getElementById("register-section").hidden = false;
    } else {
      showError(await problem(reply));
    }
  }
  await refresh(admin);
}

start();
