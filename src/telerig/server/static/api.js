"use strict";
// What every page of the control center shares to talk to its server; each page loads it before its
// own script (classic scripts: these names are the page's globals).
// A 401 means the session ended (logged out here or elsewhere, expired): api() sends the page to log
// in and throws LOGGED_OUT to stop its caller; loggedOutIsNoError() lets a catch ignore exactly that.

// The session's CSRF token (GET /api/me): every state-changing request sends it in X-CSRF-Token.
let csrf = "";

const LOGGED_OUT = "logged out";

// fetch() with the CSRF token on everything but GET, and a body sent as JSON unless told otherwise.
async function api(path, options = {}) {
  const headers = { ...(options.headers || {}) };
  if (options.method && options.method !== "GET") headers["X-CSRF-Token"] = csrf;
  if (options.body !== undefined && !("Content-Type" in headers)) headers["Content-Type"] = "application/json";
  const reply = await fetch(path, { ...options, headers });
  if (reply.status === 401) {
    window.location.assign("/login");
    throw new Error(LOGGED_OUT);
  }
  return reply;
}

// Why the server refused a request (its {"detail": ...}), as one line of text.
async function problem(reply) {
  try {
    const body = await reply.json();
    return typeof body.detail === "string" ? body.detail : JSON.stringify(body.detail);
  } catch {
    return `HTTP ${reply.status}`;
  }
}

// api(), with a reply that is not ok thrown as an Error of its detail (err.status: the HTTP status).
async function apiOk(path, options = {}) {
  const reply = await api(path, options);
  if (!reply.ok) {
    const err = new Error(await problem(reply));
    err.status = reply.status;
    throw err;
  }
  return reply;
}

// For a catch: the LOGGED_OUT of a 401 is no error (the page is on its way to log in); others are.
function loggedOutIsNoError(err) {
  if (err.message !== LOGGED_OUT) throw err;
}
