"use strict";
// Log in with a JSON body (a cross-site form cannot send one), then open the dashboard.
document.getElementById("login").addEventListener("submit", async (event) => {
  event.preventDefault();
  const form = new FormData(event.target);
  const error = document.getElementById("error");
  error.textContent = "";
  const reply = await fetch("/api/login", {
    method: "POST",
    headers: { "Content-Type": "application/json" },
    body: JSON.stringify({ user: form.get("user"), password: form.get("password") }),
  });
  if (reply.ok) {
    window.location.assign("/");
    return;
  }
  const body = await reply.json().catch(() => ({ detail: reply.statusText }));
  error.textContent = body.detail;
});
