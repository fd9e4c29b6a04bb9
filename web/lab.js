// The lab server's page (docs/lab.md, "Several robots"): every robot with
// its profile, state, experiment and time left, and a STOP for each and
// for all; the user's experiments (all of them for admins), submitting,
// cancelling, downloading results; one robot's live status on demand.
"use strict";

const $ = (id) => document.getElementById(id);
let me = null;
let watching = null;

async function api(method, path, body) {
  const response = await fetch("/api/v1" + path, {
    method,
    headers: body === undefined ? {} : { "Content-Type": "application/json" },
    body: body === undefined ? undefined : JSON.stringify(body),
    credentials: "same-origin",
  });
  const json = await response.json().catch(() => ({}));
  if (!response.ok) throw new Error(json.error || response.statusText);
  return json;
}

function cell(row, text) {
  const td = document.createElement("td");
  td.textContent = text === undefined || text === null ? "" : String(text);
  row.appendChild(td);
  return td;
}

function button(label, title, action) {
  const b = document.createElement("button");
  b.textContent = label;
  b.title = title;
  b.addEventListener("click", action);
  return b;
}

function showRobots(robots) {
  const body = $("robots").querySelector("tbody");
  body.textContent = "";
  const target = $("submit-target");
  const chosen = target.value;
  target.textContent = "";
  target.appendChild(new Option("any robot", ""));
  for (const robot of robots) {
    const row = document.createElement("tr");
    row.dataset.robot = robot.name;
    cell(row, robot.name);
    cell(row, robot.profile.id);
    const state = robot.state === "stopped" ? `stopped (${robot.stopped_by})` : robot.state;
    cell(row, state).className = "robot-state";
    cell(row, robot.experiment);
    cell(row, robot.time_left_s === null ? "" : `${Math.ceil(robot.time_left_s)} s`);
    const actions = cell(row, "");
    actions.appendChild(button("watch", "Its live status", () => watch(robot.name)));
    actions.appendChild(button("STOP", "Engage this robot's emergency stop", async () => {
      const said = await api("POST", `/robots/${encodeURIComponent(robot.name)}/stop`).catch((e) => ({ error: e.message }));
      $("stop-said").textContent = said.error || said.stopped.map((s) => `${s.robot}: ${s.message}`).join("; ");
    }));
    body.appendChild(row);
    target.appendChild(new Option(`${robot.name} (profile ${robot.profile.id})`, robot.name));
  }
  target.value = chosen;
}

function showExperiments(experiments) {
  const body = $("experiments").querySelector("tbody");
  body.textContent = "";
  for (const e of experiments) {
    const row = document.createElement("tr");
    row.dataset.experiment = e.id;
    cell(row, e.id);
    cell(row, e.submitter);
    cell(row, e.label);
    cell(row, e.state).className = "experiment-state";
    cell(row, e.placement && e.placement.robot);
    cell(row, e.place);
    const actions = cell(row, "");
    if (!["done", "refused", "cancelled", "aborted", "failed"].includes(e.state)) {
      actions.appendChild(button("cancel", "Cancel it (a running one stops, its robot goes back to its baseline)",
        () => api("POST", `/experiments/${e.id}/cancel`).catch((err) => alert(err.message))));
      if (e.state === "running" && e.placement && e.placement.robot) {
        actions.appendChild(button("watch", "Its robot's live status", () => watch(e.placement.robot)));
      }
    } else {
      const a = document.createElement("a");
      a.href = `/api/v1/experiments/${e.id}/results`;
      a.textContent = "results";
      actions.appendChild(a);
    }
    body.appendChild(row);
  }
}

async function watch(name) {
  watching = name;
  $("live-view").hidden = false;
  $("live-robot").textContent = name;
}

async function refreshLive() {
  if (!watching) return;
  try {
    const live = await api("GET", `/robots/${encodeURIComponent(watching)}/live`);
    const s = live.status || {};
    const lines = [
      `set ${s.set}, ${s.duration_s === undefined ? "" : s.duration_s.toFixed(1) + " s"}`,
      `experiment: ${s.experiment ? JSON.stringify(s.experiment) : "none"}`,
    ];
    $("live-status").textContent = lines.join("\n") + "\n\n" + JSON.stringify(s, null, 1).slice(0, 4000);
  } catch (e) {
    $("live-status").textContent = e.message;
  }
}

function listen() {
  const events = new EventSource("/api/v1/lab/events");
  events.addEventListener("lab", (event) => {
    const snapshot = JSON.parse(event.data);
    showRobots(snapshot.lab.robots || []);
    showExperiments(snapshot.experiments || []);
  });
  setInterval(async () => {
    const robots = await api("GET", "/robots").catch(() => null);
    if (robots) showRobots(robots.robots);
    refreshLive();
  }, 1000);
}

const ROLES_THAT_SUBMIT = ["researcher", "developer", "admin"];

async function start() {
  try {
    me = await api("GET", "/session");
  } catch {
    return;
  }
  $("login-view").hidden = true;
  $("app").hidden = false;
  $("stop-bar").hidden = false;
  $("whoami").textContent = `${me.name} (${me.role})`;
  // Only the roles that may submit see the form (the robot portal's
  // ROLE_MAY `lab` column; the API refuses the others with 403).
  $("submit-section").hidden = !ROLES_THAT_SUBMIT.includes(me.role);
  listen();
}

$("login-form").addEventListener("submit", async (event) => {
  event.preventDefault();
  try {
    await api("POST", "/login", { name: $("login-name").value, password: $("login-password").value });
    $("login-error").textContent = "";
    start();
  } catch (e) {
    $("login-error").textContent = e.message;
  }
});

$("stop-all").addEventListener("click", async () => {
  const said = await api("POST", "/robots/stop").catch((e) => ({ error: e.message }));
  $("stop-said").textContent = said.error || said.stopped.map((s) => `${s.robot}: ${s.message}`).join("; ");
});

$("submit-form").addEventListener("submit", async (event) => {
  event.preventDefault();
  const body = {
    set: Number($("submit-set").value),
    duration_s: Number($("submit-duration").value),
    label: $("submit-label").value,
  };
  if ($("submit-target").value) body.target = { robot: $("submit-target").value };
  try {
    const created = await api("POST", "/experiments", body);
    $("submit-said").textContent = `experiment ${created.experiment.id} submitted`;
  } catch (e) {
    $("submit-said").textContent = e.message;
  }
});

$("live-close").addEventListener("click", () => {
  watching = null;
  $("live-view").hidden = true;
});

start();
