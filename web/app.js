// The subsume portal: plain JavaScript, no build step. Talks to /api/v1
// (see /api/v1/openapi.json) with the session cookie set at login.
'use strict';

const $ = (id) => document.getElementById(id);
const el = (tag, attrs = {}, ...children) => {
  const node = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) node.setAttribute(k, v);
  for (const c of children) node.append(c);
  return node;
};

async function api(method, path, body, headers = {}) {
  const response = await fetch('/api/v1' + path, { method, body, headers, credentials: 'same-origin' });
  const data = response.status === 204 ? {} : await response.json().catch(() => ({}));
  if (!response.ok) {
    const error = new Error(data.error || response.statusText);
    error.status = response.status;
    error.body = data;
    error.retryAfter = response.headers.get('retry-after');
    throw error;
  }
  return data;
}

let me = null;
let world = null;
let events = null;

// ---- login ---------------------------------------------------------------
$('login-form').addEventListener('submit', async (e) => {
  e.preventDefault();
  $('login-error').textContent = '';
  try {
    const body = JSON.stringify({ name: $('login-name').value, password: $('login-password').value });
    const result = await api('POST', '/login', body, { 'content-type': 'application/json' });
    start(result.user);
  } catch (err) {
    $('login-error').textContent = err.message;
  }
});

async function boot() {
  try {
    start(await api('GET', '/session'));
  } catch (err) {
    $('login-view').hidden = false;
  }
}

function start(user) {
  me = user;
  $('login-view').hidden = true;
  $('app').hidden = false;
  $('tabs').hidden = false;
  $('whoami').textContent = `${user.name} (${user.role}${user.platforms.length ? ': ' + user.platforms.join(', ') : ''})`;
  const logout = el('button', { id: 'logout' }, 'Log out');
  logout.addEventListener('click', async () => { await api('POST', '/logout').catch(() => {}); location.reload(); });
  $('whoami').append(' ', logout);
  $('estop-bar').hidden = false;
  applyRole();
  refreshLocks();
  startLive();
  refreshComponents();
  refreshSets();
  startLab();
}

// ---- what each role sees -------------------------------------------------
// Each role sees only the controls it may use: what it may not use is
// hidden, not merely disabled. One row per role, saying what the host lets
// it do (host/src/deploy/mod.rs `authorise`, host/src/store/users.rs):
//   drive     the pad, the simulator's buttons, releasing a stop
//   change    upload components and robot files, edit them: 'all'
//             platforms, the session's 'platforms', or 'none'
//   activate  activate a set, roll back
//   record    recordings, and replaying a set against one
// A new role is one more row. An element says what it needs with
// data-may="drive", "change" (any platform) or "change:PLATFORM".
//   lab       the Lab tab: submit experiments, book reservations, the kit
//   admin     the lab's settings, every experiment's submitter, confirming
//             a manual reset, booking for someone else
// Inside a reservation of one's own (docs/lab.md), any user may drive.
const ROLE_MAY = {
  viewer:     { drive: false, change: 'none',      activate: false, record: false, lab: false, admin: false },
  operator:   { drive: true,  change: 'none',      activate: false, record: false, lab: false, admin: false },
  researcher: { drive: false, change: 'platforms', activate: false, record: false, lab: true,  admin: false },
  developer:  { drive: false, change: 'platforms', activate: true,  record: true,  lab: true,  admin: false },
  admin:      { drive: true,  change: 'all',       activate: true,  record: true,  lab: true,  admin: true },
};
// Whether the reservation in effect now is the user's (the lab's view says).
let reservedByMe = false;
function applyRoles(reservedNow = null) {
  const mine = Boolean(me && reservedNow && reservedNow.user === me.name);
  if (mine === reservedByMe) return;
  reservedByMe = mine;
  applyRole();
}
function may(what) {
  const row = (me && ROLE_MAY[me.role]) || {};
  const [permission, platform] = what.split(':');
  if (permission === 'drive' && reservedByMe) return true;
  if (permission !== 'change') return row[permission] === true;
  if (row.change === 'all') return true;
  if (row.change !== 'platforms') return false;
  return platform ? me.platforms.includes(platform) : me.platforms.length > 0;
}
// Hides every element under `root` whose data-may the user lacks; a
// select whose chosen option is hidden moves to the first one shown.
function applyRole(root = document) {
  for (const node of root.querySelectorAll('[data-may]')) {
    node.hidden = !may(node.dataset.may);
    if (node.tagName === 'OPTION') node.disabled = node.hidden;
  }
  for (const select of root.querySelectorAll('select')) {
    const chosen = select.selectedOptions[0];
    if (chosen && chosen.hidden) {
      const shown = [...select.options].find((o) => !o.hidden);
      if (shown) select.value = shown.value;
    }
  }
}

// ---- emergency stop (docs/estop.md) --------------------------------------
// STOP on every tab for every logged-in user; release is a separate,
// confirmed action, offered to users who may drive.
const mayDrive = () => may('drive');
function renderLocks(engaged) {
  const banner = $('lock-banner');
  if (!engaged || engaged.length === 0) {
    banner.textContent = '';
    document.body.classList.remove('locked');
    $('release').hidden = true;
    return;
  }
  document.body.classList.add('locked');
  banner.textContent = 'STOPPED: ' + engaged.map((e) => `${e.lock} by ${e.by} over ${e.how} since ${new Date(e.since_ms).toLocaleTimeString()}`).join('; ');
  $('release').hidden = !mayDrive();
}
async function refreshLocks() {
  try { renderLocks((await api('GET', '/locks')).engaged); } catch (err) { /* shown on the next status */ }
}
$('estop').addEventListener('click', async () => {
  try {
    renderLocks((await api('POST', '/estop')).engaged);
  } catch (err) {
    $('lock-banner').textContent = 'the stop failed: ' + err.message;
  }
});
$('release').addEventListener('click', async () => {
  if (!confirm('Release the emergency stop? The robot may move at once.')) return;
  try {
    await api('POST', '/release');
  } catch (err) {
    $('lock-banner').textContent = 'release refused: ' + err.message;
    return;
  }
  refreshLocks();
});

// ---- tabs ----------------------------------------------------------------
for (const button of document.querySelectorAll('#tabs button')) {
  button.addEventListener('click', () => {
    for (const b of document.querySelectorAll('#tabs button')) b.classList.toggle('active', b === button);
    for (const tab of document.querySelectorAll('.tab')) tab.hidden = tab.id !== 'tab-' + button.dataset.tab;
    if (button.dataset.tab === 'components') refreshComponents();
    if (button.dataset.tab === 'sets') { refreshSets(); if (may('record')) refreshReplayRecordings(); refreshWorlds(); }
    if (button.dataset.tab === 'recordings') refreshRecordings();
    if (button.dataset.tab === 'lab') { refreshLabSets(); renderLab(); }
  });
}
function showTab(name) { document.querySelector(`#tabs button[data-tab="${name}"]`).click(); }

// ---- live view -----------------------------------------------------------
// The running cameras live, each an MJPEG stream an <img> plays, for those
// who may watch them (the owner, operators, a researcher during her own
// experiment: docs/portal.md); nothing for the rest. Asked again when the
// set changes (a researcher's experiment starts or ends).
async function refreshCameras() {
  const box = $('cameras');
  let names = [];
  try { names = (await api('GET', '/cameras')).cameras; } catch (err) { names = []; }
  box.replaceChildren(...names.map((name) => el('figure', {},
    el('img', { src: `/api/v1/cameras/${encodeURIComponent(name)}/live?set=${$('active-set').dataset.set || ''}`, alt: `camera ${name} live`, 'data-camera': name }),
    el('figcaption', {}, `camera ${name}`))));
  box.hidden = names.length === 0;
}

async function startLive() {
  try { world = await api('GET', '/world'); } catch (err) { world = null; $('map-note').textContent = err.message; }
  // The cameras come with the first status (its set is new to the page):
  // asked here too, each <img> would be made twice and its stream cut.
  await loadPlotHistory();
  if (events) events.close();
  events = new EventSource('/api/v1/events');
  events.addEventListener('status', (e) => renderStatus(JSON.parse(e.data)));
  events.addEventListener('log', (e) => {
    const line = JSON.parse(e.data);
    const log = $('log');
    log.append(el('li', {}, `${new Date(line.time * 1000).toLocaleTimeString()} ${line.level} ${line.component ? line.component + ': ' : ''}${line.message}`));
    while (log.children.length > 200) log.firstChild.remove();
    log.scrollTop = log.scrollHeight;
  });
}

const rates = new Map();
function renderStatus(s) {
  if (!s || !s.components) return;
  if (String(s.set) !== $('active-set').dataset.set) {
    $('active-set').dataset.set = String(s.set);
    api('GET', '/world').then((w) => { world = w; }).catch(() => { world = null; });
    refreshCameras();
  }
  $('active-set').textContent = `set ${s.set} (${s.robot})`;
  // Whose code drives (docs/lab.md): the experiment the set runs as.
  const tag = s.experiment;
  $('experiment-tag').textContent = tag ? `experiment ${tag.id} by ${tag.submitter}${tag.label ? ` ('${tag.label}')` : ''}` : 'no experiment: the robot\'s own set';
  const arbiter = s.arbiter || {};
  if (arbiter.engaged) renderLocks(arbiter.engaged);
  $('holder').textContent = arbiter.holder || 'nobody (STOP)';
  $('suppressed').textContent = (arbiter.suppressed || []).join(', ') || '-';
  const sessions = (s.teleop && s.teleop.sessions || []).filter((x) => x.disconnected_at_s == null && x.operator);
  $('mode').textContent = sessions.map((x) => `${x.operator}: ${x.mode || 'none'}`).join(', ') || 'no operator';
  $('rtt').textContent = sessions.map((x) => x.rtt_ms == null ? 'measuring' : `${x.rtt_ms.toFixed(1)} ms`).join(', ') || '-';
  const sim = s.sim;
  if (sim) {
    $('pose').textContent = `x ${sim.x.toFixed(2)} y ${sim.y.toFixed(2)} heading ${sim.heading.toFixed(2)}`;
    $('collisions').textContent = String(sim.collisions);
  }
  const body = $('health').querySelector('tbody');
  body.replaceChildren();
  for (const c of s.components) {
    const before = rates.get(c.name);
    const now = { t: s.duration_s, i: c.messages_in, o: c.messages_out, set: s.set };
    rates.set(c.name, now);
    // Counters restart with each activated set: no rate across a swap.
    const rate = (k) => before && now.t > before.t && now[k] >= before[k] && s.set === before.set ? ((now[k] - before[k]) / (now.t - before.t)).toFixed(1) : '-';
    const state = el('td', { class: c.state }, c.state + (c.fault ? ': ' + c.fault : ''));
    const sha = tag && tag.sha256 && tag.sha256[c.name];
    const hash = el('td', { class: 'sha', title: sha || '' }, sha ? sha.slice(0, 12) : '-');
    body.append(el('tr', { 'data-component': c.name }, el('td', {}, c.name), state, el('td', {}, rate('i')), el('td', {}, rate('o')), el('td', {}, String(c.restarts)), hash));
  }
  const envelope = s.envelope;
  if (envelope) {
    const closest = envelope.closest_ever_m == null ? '-' : `${envelope.closest_ever_m.toFixed(2)} m`;
    $('envelope').textContent = `passed ${envelope.passed}, scaled ${envelope.scaled}, stopped ${envelope.stopped}; closest approach ${closest}`;
    $('intervention').textContent = envelope.last ? `${envelope.last.at_s.toFixed(1)} s: ${envelope.last.text}` : '-';
  } else {
    $('envelope').textContent = 'none';
    $('intervention').textContent = '-';
  }
  // Zenoh and ROS 2 bridges (docs/distributed.md): one line each.
  const bridges = Object.keys(s).filter((k) => /^(zenoh|ros2)(:|$)/.test(k)).map((k) => s[k]);
  $('bridges').textContent = bridges.length === 0 ? 'none' : bridges.map((b) => {
    const seen = b.last_seen_s_ago == null ? 'never' : `${b.last_seen_s_ago.toFixed(1)} s ago`;
    return `${b.key}: peers ${b.peers}, in ${b.in}, out ${b.out}, malformed ${b.malformed}, dropped ${b.dropped}, last seen ${seen}`;
  }).join('\n');
  drawMap(sim, envelope);
  viewsOnStatus(s);
  labOnStatus(s);
}

function drawMap(sim, envelope, canvas = $('map')) {
  const ctx = canvas.getContext('2d');
  ctx.clearRect(0, 0, canvas.width, canvas.height);
  if (!world) return;
  const [lo, hi] = world.world.bounds;
  const scale = Math.min((canvas.width - 20) / (hi.x - lo.x), (canvas.height - 20) / (hi.y - lo.y));
  const X = (x) => 10 + (x - lo.x) * scale;
  const Y = (y) => canvas.height - 10 - (y - lo.y) * scale;
  ctx.strokeStyle = '#333'; ctx.lineWidth = 2;
  for (const o of world.world.obstacles) {
    ctx.beginPath();
    if (o.segment) { ctx.moveTo(X(o.segment[0].x), Y(o.segment[0].y)); ctx.lineTo(X(o.segment[1].x), Y(o.segment[1].y)); }
    if (o.circle) { ctx.arc(X(o.circle[0].x), Y(o.circle[0].y), o.circle[1] * scale, 0, 2 * Math.PI); }
    ctx.stroke();
  }
  const [goal, tolerance] = world.world.goal;
  ctx.fillStyle = '#11772b';
  ctx.beginPath(); ctx.arc(X(goal.x), Y(goal.y), Math.max(4, tolerance * scale), 0, 2 * Math.PI); ctx.fill();
  const zones = envelope && envelope.settings;
  if (zones && zones.geofence && zones.geofence.length >= 3) {
    // The geofence, in odometry coordinates (the simulator's world frame).
    ctx.strokeStyle = 'rgba(200, 0, 0, 0.8)'; ctx.lineWidth = 1; ctx.setLineDash([6, 4]);
    ctx.beginPath();
    zones.geofence.forEach(([x, y], i) => (i ? ctx.lineTo(X(x), Y(y)) : ctx.moveTo(X(x), Y(y))));
    ctx.closePath(); ctx.stroke(); ctx.setLineDash([]);
  }
  if (!sim) return;
  if (zones) {
    // Slowdown and stop zones around the footprint.
    for (const [extra, colour] of [[zones.slow_distance, 'rgba(230, 160, 0, 0.25)'], [zones.stop_distance, 'rgba(220, 0, 0, 0.35)']]) {
      ctx.fillStyle = colour;
      ctx.beginPath(); ctx.arc(X(sim.x), Y(sim.y), (zones.radius + extra) * scale, 0, 2 * Math.PI); ctx.fill();
    }
  }
  const rays = sim.ranges || [];
  const fov = world.fov || Math.PI;
  ctx.strokeStyle = 'rgba(255, 120, 0, 0.6)'; ctx.lineWidth = 1;
  rays.forEach((range, i) => {
    const angle = sim.heading + (rays.length > 1 ? -fov / 2 + (fov * i) / (rays.length - 1) : 0);
    ctx.beginPath();
    ctx.moveTo(X(sim.x), Y(sim.y));
    ctx.lineTo(X(sim.x + range * Math.cos(angle)), Y(sim.y + range * Math.sin(angle)));
    ctx.stroke();
  });
  const radius = (world.radius || 0.2) * scale;
  ctx.fillStyle = '#0b5cad';
  ctx.beginPath(); ctx.arc(X(sim.x), Y(sim.y), radius, 0, 2 * Math.PI); ctx.fill();
  ctx.strokeStyle = '#fff'; ctx.lineWidth = 2; ctx.beginPath();
  ctx.moveTo(X(sim.x), Y(sim.y));
  ctx.lineTo(X(sim.x + 0.3 * Math.cos(sim.heading)), Y(sim.y + 0.3 * Math.sin(sim.heading)));
  ctx.stroke();
  // Where the robot was drawn and with how many rays (the browser tests read it).
  canvas.dataset.robot = `${X(sim.x).toFixed(1)},${Y(sim.y).toFixed(1)}`;
  canvas.dataset.rays = String(rays.length);
}

// ---- components ----------------------------------------------------------
let chosen = null;
function choose(file) {
  chosen = file;
  if (!$('component-name').value) $('component-name').value = file.name.replace(/\.wasm$/, '').replace(/_/g, '-').toLowerCase();
  $('component-upload').disabled = false;
  $('upload-result').textContent = `${file.name}: ${(file.size / 1024).toFixed(0)} KiB`;
}
$('component-file').addEventListener('change', (e) => { if (e.target.files[0]) choose(e.target.files[0]); });
const zone = $('drop-zone');
zone.addEventListener('dragover', (e) => { e.preventDefault(); zone.classList.add('over'); });
zone.addEventListener('dragleave', () => zone.classList.remove('over'));
zone.addEventListener('drop', (e) => { e.preventDefault(); zone.classList.remove('over'); if (e.dataTransfer.files[0]) choose(e.dataTransfer.files[0]); });

$('component-upload').addEventListener('click', () => {
  if (!chosen) return;
  const name = $('component-name').value.trim();
  const platform = $('component-platform').value;
  const xhr = new XMLHttpRequest();
  const progress = $('upload-progress');
  progress.hidden = false; progress.value = 0;
  xhr.upload.onprogress = (e) => { if (e.lengthComputable) progress.value = e.loaded / e.total; };
  const compiling = compileProgress(name);
  xhr.upload.onload = compiling.start;
  xhr.onload = () => {
    progress.hidden = true;
    const took = compiling.stop();
    const data = JSON.parse(xhr.responseText || '{}');
    const result = $('upload-result');
    if (xhr.status === 201) {
      result.className = 'ok';
      result.textContent = `stored '${data.name}' as ${data.uploaded_by}/${data.name} (${data.world}, sha256 ${data.sha256.slice(0, 12)}...)${took}; your robot files name it ${data.name}.wasm, anyone's ${data.source}`;
      refreshComponents();
    } else {
      result.className = 'error';
      result.textContent = `refused (${xhr.status}): ${data.error || xhr.statusText}`;
    }
  };
  xhr.onerror = () => { progress.hidden = true; compiling.stop(); $('upload-result').textContent = 'upload failed: no answer from the robot'; };
  xhr.open('PUT', `/api/v1/platforms/${platform}/components/${encodeURIComponent(name)}`);
  xhr.setRequestHeader('content-type', 'application/wasm');
  xhr.send(chosen);
});

// Once the bytes are sent, the robot compiles and checks the component
// before it answers (seconds for a Python or JavaScript one, less when its
// functions are in the robot's compile cache): say so, with the seconds
// ticking, and how long it took. stop() returns ', compiled and checked in
// T s' for the result line (empty if the upload never finished sending).
function compileProgress(name) {
  const result = $('upload-result');
  let started = null;
  let timer = null;
  const show = () => {
    const seconds = ((performance.now() - started) / 1000).toFixed(0);
    result.className = '';
    result.dataset.compiling = seconds;
    result.textContent = `uploaded '${name}'; the robot is compiling and checking it... ${seconds} s`;
  };
  return {
    start() { started = performance.now(); show(); timer = setInterval(show, 500); },
    stop() {
      clearInterval(timer);
      delete result.dataset.compiling;
      if (started === null) return '';
      const seconds = (performance.now() - started) / 1000;
      result.dataset.compileSeconds = seconds.toFixed(2);
      return `, compiled and checked in ${seconds.toFixed(1)} s`;
    },
  };
}

function portList(title, ports) {
  return el('p', {}, `${title}: `, ports.length ? ports.map((p) => `${p.name} (${p.kind})`).join(', ') : 'none');
}

async function refreshComponents() {
  const list = $('component-list');
  try {
    const { components } = await api('GET', '/components');
    // Each upload is its uploader's: yours first, then everyone else's.
    const mine = (c) => (me && c.uploaded_by === me.name ? 0 : 1);
    components.sort((a, b) => mine(a) - mine(b) || a.source.localeCompare(b.source));
    list.replaceChildren(...components.map((c) => {
      const d = c.description || {};
      const whose = mine(c) === 0 ? 'yours: name it ' + c.name + '.wasm' : 'by ' + c.uploaded_by + ': name it ' + c.source;
      const box = el('div', { class: 'component', 'data-component': c.name, 'data-owner': c.uploaded_by },
        el('h3', {}, `${c.uploaded_by}/${c.name} `, el('small', {}, `${c.world}, ${(c.size / 1024).toFixed(0)} KiB, ${whose}`)));
      if (d.inputs) {
        box.append(el('p', {}, `${d.name} ${d.version}: ${d.summary}`));
        box.append(portList('inputs', d.inputs), portList('outputs', d.outputs));
        box.append(el('p', {}, 'parameters: ' + (d.params.map((p) => `${p.name}=${p.default}`).join(', ') || 'none')));
      }
      return box;
    }));
    if (!components.length) list.textContent = 'none yet';
  } catch (err) {
    list.textContent = err.message;
  }
}

// An upload's refusal: the message on the result line, and each located
// diagnostic (file:line:column: message) as an item of the errors list.
function showRefusal(err, resultId, errorsId) {
  $(resultId).className = 'error';
  $(resultId).textContent = err.message;
  for (const d of (err.body && err.body.diagnostics) || []) $(errorsId).append(el('li', {}, d.text));
}

// ---- robot files and sets ------------------------------------------------
$('config-upload').addEventListener('click', async () => {
  const file = $('config-file').files[0];
  $('config-errors').replaceChildren();
  $('config-result').textContent = '';
  if (!file) { $('config-result').textContent = 'choose a robot file first'; return; }
  try {
    const platform = $('config-platform').value;
    const { set } = await api('PUT', `/platforms/${platform}/configs/${encodeURIComponent(file.name)}`, await file.text(), { 'content-type': 'application/xml' });
    $('config-result').className = 'ok';
    $('config-result').textContent = `valid: staged as set ${set.id} (changes: ${set.changes.join(', ') || 'nothing'})`;
    await refreshSets();
    showGraph(set.id);
  } catch (err) {
    showRefusal(err, 'config-result', 'config-errors');
  }
});

async function refreshSets() {
  const body = $('set-list').querySelector('tbody');
  try {
    const { sets } = await api('GET', '/sets');
    body.replaceChildren(...sets.map((s) => {
      const show = el('button', { class: 'show', 'data-set': s.id }, 'wiring');
      show.addEventListener('click', () => showGraph(s.id));
      const cells = [el('td', {}, String(s.id)), el('td', {}, s.config_name), el('td', {}, s.created_by), el('td', {}, s.changes.join(', ')), el('td', { class: 'status' }, s.status)];
      const actions = el('td', {}, show);
      if (s.status !== 'active') {
        const activate = el('button', { class: 'activate', 'data-set': s.id, 'data-may': 'activate' }, 'activate');
        activate.addEventListener('click', () => activateSet(s.id));
        actions.append(' ', activate);
        actions.append(' ', replayButton(s.id));
      }
      return el('tr', { 'data-set': s.id }, ...cells, actions);
    }));
    applyRole(body);
    const active = sets.find((s) => s.status === 'active');
    if (active && $('graph-set').textContent === '-') showGraph(active.id);
  } catch (err) {
    $('set-result').textContent = err.message;
  }
}

async function activateSet(id) {
  $('set-result').className = '';
  $('set-result').textContent = `activating set ${id}...`;
  try {
    await api('POST', `/sets/${id}/activate`);
    $('set-result').className = 'ok';
    $('set-result').textContent = `set ${id} is active`;
  } catch (err) {
    $('set-result').className = 'error';
    $('set-result').textContent = `set ${id} was not activated: ${err.message}`;
  }
  refreshSets();
}

$('rollback').addEventListener('click', async () => {
  try {
    const { active } = await api('POST', '/rollback');
    $('set-result').className = 'ok';
    $('set-result').textContent = `rolled back: set ${active.id} is active`;
  } catch (err) {
    $('set-result').className = 'error';
    $('set-result').textContent = `no rollback: ${err.message}`;
  }
  refreshSets();
});

async function showGraph(id) {
  const svg = $('graph');
  svg.replaceChildren();
  $('graph-set').textContent = String(id);
  const { graph, overrides } = await api('GET', `/sets/${id}`);
  $('graph-overrides').textContent = (overrides || []).length
    ? 'In effect beyond the file (subsume run --param): ' +
      overrides.map((o) => `${o.component}.${o.param}=${o.value}`).join(', ')
    : '';
  if (!graph.components) { $('set-result').textContent = graph.error; return; }
  // Layers: components in data-flow order (flowOrder); an edge is forward
  // when it goes to a later component, and a component sits one layer
  // right of its deepest forward source. Back edges (feedback loops, e.g.
  // envelope -> motors) curve below.
  const names = graph.components.map((c) => c.name);
  const edges = graph.connections.map((c) => [c.from.split('.')[0], c.to.split('.')[0], c]);
  const order = flowOrder(names, edges);
  const forward = ([a, b]) => order.get(a) < order.get(b);
  const layer = new Map(names.map((n) => [n, 0]));
  for (const n of [...names].sort((x, y) => order.get(x) - order.get(y))) {
    for (const e of edges) if (e[1] === n && forward(e)) layer.set(n, Math.max(layer.get(n), layer.get(e[0]) + 1));
  }
  const rows = new Map();
  const pos = new Map();
  for (const n of [...names].sort((x, y) => order.get(x) - order.get(y))) {
    const l = layer.get(n);
    const r = rows.get(l) || 0;
    rows.set(l, r + 1);
    pos.set(n, { x: 10 + l * 170, y: 20 + r * 70 });
  }
  const width = 20 + (Math.max(...layer.values()) + 1) * 170;
  const height = 80 + Math.max(...rows.values()) * 70;
  svg.setAttribute('viewBox', `0 0 ${width} ${height}`);
  svg.setAttribute('height', String(Math.min(600, height)));
  const ns = 'http://www.w3.org/2000/svg';
  const add = (tag, attrs, text) => {
    const n = document.createElementNS(ns, tag);
    for (const [k, v] of Object.entries(attrs)) n.setAttribute(k, v);
    if (text) n.textContent = text;
    svg.append(n);
    return n;
  };
  wiringArrowheads(add);
  for (const e of edges) {
    const [a, b, c] = e;
    const p = pos.get(a), q = pos.get(b);
    const stroke = c.platform === 'network' ? '#b36b00' : '#567';
    const marker = c.platform === 'network' ? 'url(#arrow-network)' : 'url(#arrow)';
    const tag = { class: 'edge', 'data-from': c.from, 'data-to': c.to, 'marker-end': marker };
    let line;
    if (forward(e)) {
      // Data flows left to right: out of the source's right side into the
      // target's left side.
      line = add('line', { ...tag, x1: p.x + 140, y1: p.y + 20, x2: q.x - 2, y2: q.y + 20, stroke, 'stroke-width': 1.5 });
    } else {
      const low = height - 15;
      line = add('path', { ...tag, 'data-back': '1', d: `M ${p.x + 70} ${p.y + 40} C ${p.x + 70} ${low}, ${q.x + 70} ${low}, ${q.x + 70} ${q.y + 42}`, fill: 'none', stroke, 'stroke-width': 1.5, 'stroke-dasharray': '4 3' });
    }
    const title = document.createElementNS(ns, 'title');
    title.textContent = `${c.from} -> ${c.to}`;
    line.append(title);
  }
  for (const c of graph.components) {
    const p = pos.get(c.name);
    add('rect', { x: p.x, y: p.y, width: 140, height: 40, rx: 6, fill: c.platform === 'network' ? '#fff4e0' : '#e8f0fb', stroke: '#345', 'data-component': c.name });
    add('text', { x: p.x + 6, y: p.y + 16 }, c.name + (c.priority != null ? ` (p${c.priority})` : ''));
    add('text', { x: p.x + 6, y: p.y + 32, fill: '#567' }, c.source);
  }
}

// ---- drive ---------------------------------------------------------------
let socket = null;
let seq = 0;
const started = performance.now();
function driveLog(text) {
  const log = $('drive-log');
  log.append(el('li', {}, text));
  while (log.children.length > 50) log.firstChild.remove();
}
function send(message) { if (socket && socket.readyState === WebSocket.OPEN) socket.send(JSON.stringify(message)); }

$('drive-connect').addEventListener('click', async () => {
  if (socket) { send({ type: 'quit' }); socket.close(); socket = null; $('drive-connect').textContent = 'Connect'; return; }
  let ticket;
  try { ticket = await api('POST', '/teleop/ticket'); } catch (err) { $('drive-status').textContent = err.message; return; }
  const url = (location.protocol === 'https:' ? 'wss://' : 'ws://') + location.host + ticket.websocket;
  socket = new WebSocket(url);
  $('drive-connect').textContent = 'Disconnect';
  socket.onopen = () => send({ type: 'auth', name: ticket.name, token: ticket.ticket });
  socket.onclose = () => { $('drive-status').textContent = 'not connected'; socket = null; $('drive-connect').textContent = 'Connect'; };
  socket.onmessage = (e) => {
    const m = JSON.parse(e.data);
    if (m.type === 'ping') { send({ type: 'pong', nonce: m.nonce }); return; }
    if (m.type === 'rtt') {
      $('drive-status').textContent = `rtt ${m.rtt_ms.toFixed(1)} ms; allowed: ${m.allowed.join(', ')}`;
      if (m.allowed.includes($('drive-mode').value)) send({ type: 'mode', mode: $('drive-mode').value });
    }
    if (m.type === 'mode') $('drive-status').dataset.mode = m.mode;
    if (m.type === 'control') {
      $('drive-status').dataset.control = m.state;
      $('drive-status').textContent = m.message;
    }
    driveLog(JSON.stringify(m));
  };
});
$('drive-mode').addEventListener('change', () => send({ type: 'mode', mode: $('drive-mode').value }));

function command(text) {
  seq += 1;
  send({ type: 'cmd', seq, time_ms: Math.round(performance.now() - started), command: text });
}
let held = null;
for (const button of document.querySelectorAll('#pad button')) {
  const text = button.dataset.stop ? 'STOP' : `VEL ${button.dataset.v} ${button.dataset.w}`;
  const press = () => { command(text); clearInterval(held); if (!button.dataset.stop) held = setInterval(() => command(text), 100); };
  const release = () => { clearInterval(held); held = null; };
  button.addEventListener('pointerdown', press);
  button.addEventListener('pointerup', release);
  button.addEventListener('pointerleave', release);
}
document.addEventListener('keydown', (e) => {
  if ($('tab-drive').hidden || !socket) return;
  const keys = { ArrowUp: 'pad-forward', ArrowDown: 'pad-back', ArrowLeft: 'pad-left', ArrowRight: 'pad-right', ' ': 'pad-stop' };
  const id = keys[e.key];
  if (id) { e.preventDefault(); const b = $(id); command(b.dataset.stop ? 'STOP' : `VEL ${b.dataset.v} ${b.dataset.w}`); }
});

boot();

// ---- simulator controls (POST /sim/ACTION; those who may drive) -----------
for (const button of document.querySelectorAll('#sim-controls button[data-sim]')) {
  button.addEventListener('click', async () => {
    try {
      const sim = await api('POST', '/sim/' + button.dataset.sim);
      $('sim-result').textContent =
        `t = ${sim.time_s.toFixed(2)} s at (${sim.x.toFixed(2)}, ${sim.y.toFixed(2)})`;
    } catch (err) {
      $('sim-result').textContent = `refused: ${err.message}`;
    }
  });
}

// Set pose: the robot put at (x, y, heading) from the three fields, at rest.
$('sim-pose').addEventListener('click', async () => {
  const query = ['x', 'y', 'heading'].map((k) => `${k}=${encodeURIComponent($('sim-pose-' + k).value)}`).join('&');
  try {
    const sim = await api('POST', '/sim/pose?' + query);
    $('sim-result').textContent =
      `t = ${sim.time_s.toFixed(2)} s at (${sim.x.toFixed(2)}, ${sim.y.toFixed(2)}) heading ${sim.heading.toFixed(2)}`;
  } catch (err) {
    $('sim-result').textContent = `refused: ${err.message}`;
  }
});

// ---- the portal's own views (docs/portal.md): the Drive tab's map, -------
// ---- history plots, the robot-file editor ---------------------------------

// The history plots start with what the host kept (loadPlotHistory), then
// add what this page sees of the live status (5 a second), for
// PLOT_WINDOW_S: a page left open for days holds at most this many samples
// (MAX_PLOT_SAMPLES) and draws in bounded time.
const PLOT_WINDOW_S = 300;
const MAX_PLOT_SAMPLES = 2000;
const plotHistory = [];
const plotLast = new Map();
const PLOT_COLOURS = ['#0b5cad', '#c62828', '#11772b', '#b36b00', '#6a1b9a', '#00838f', '#5d4037', '#ad1457'];

function viewsOnStatus(s) {
  const now = Date.now() / 1000;
  const rtt = {};
  for (const x of (s.teleop && s.teleop.sessions) || []) {
    if (x.disconnected_at_s == null && x.operator && x.rtt_ms != null) rtt[x.operator] = x.rtt_ms;
  }
  const rates = {};
  for (const c of s.components) {
    const before = plotLast.get(c.name);
    const here = { t: s.duration_s, o: c.messages_out, set: s.set };
    plotLast.set(c.name, here);
    // Counters restart with each activated set: no rate across a swap.
    if (before && here.set === before.set && here.t > before.t && here.o >= before.o) {
      rates[c.name] = (here.o - before.o) / (here.t - before.t);
    }
  }
  const arbiter = s.arbiter || {};
  plotHistory.push({ t: now, rtt, rates, holder: arbiter.holder || (s.arbiter ? 'STOP' : 'no arbiter') });
  while (plotHistory.length > MAX_PLOT_SAMPLES || (plotHistory.length && plotHistory[0].t < now - PLOT_WINDOW_S)) plotHistory.shift();
  if (!$('tab-live').hidden) {
    drawLines($('plot-rtt'), 'rtt', now);
    drawLines($('plot-rates'), 'rates', now);
    drawHolder($('plot-holder'), now);
  }
  if (!$('tab-drive').hidden) {
    drawMap(s.sim, s.envelope, $('drive-map'));
    $('drive-pose').textContent = s.sim
      ? `x ${s.sim.x.toFixed(2)} y ${s.sim.y.toFixed(2)} heading ${s.sim.heading.toFixed(2)}; holds control: ${arbiter.holder || 'nobody (STOP)'}`
      : (world ? '' : 'the active set has no simulator (builtin:sim): no map');
  }
}
$('plot-window').textContent = String(PLOT_WINDOW_S / 60);

// The history the host kept (GET /history: a sample a second, its last
// minutes), so a page opened now plots them at once; the live events then
// go on from there. Host times are graph seconds: placed on this page's
// clock by the host's "now".
async function loadPlotHistory() {
  let history;
  try { history = await api('GET', '/history'); } catch (err) { return; }
  const now = Date.now() / 1000;
  plotHistory.length = 0;
  plotLast.clear();
  for (const h of history.samples) {
    plotHistory.push({ t: now - (history.now_s - h.t_s), rtt: h.rtt_ms, rates: h.rates, holder: h.holder });
  }
  while (plotHistory.length > MAX_PLOT_SAMPLES || (plotHistory.length && plotHistory[0].t < now - PLOT_WINDOW_S)) plotHistory.shift();
  // What came from the host (the browser tests read it).
  for (const id of ['plot-rtt', 'plot-rates', 'plot-holder']) {
    $(id).dataset.history = String(plotHistory.length);
    $(id).dataset.historySpan = plotHistory.length ? String(now - plotHistory[0].t) : '0';
  }
  drawLines($('plot-rtt'), 'rtt', now);
  drawLines($('plot-rates'), 'rates', now);
  drawHolder($('plot-holder'), now);
}

// Time axis: what the page saw, at least the last minute and at most
// PLOT_WINDOW_S seconds, now at the right edge.
function plotSpan(now) {
  const seen = plotHistory.length ? now - plotHistory[0].t : 0;
  return Math.min(PLOT_WINDOW_S, Math.max(60, seen));
}
function plotFrame(canvas, now) {
  const span = plotSpan(now);
  const ctx = canvas.getContext('2d');
  ctx.clearRect(0, 0, canvas.width, canvas.height);
  const box = { left: 40, right: canvas.width - 110, top: 8, bottom: canvas.height - 18 };
  ctx.strokeStyle = '#ccd'; ctx.lineWidth = 1;
  ctx.strokeRect(box.left, box.top, box.right - box.left, box.bottom - box.top);
  ctx.fillStyle = '#5b6570'; ctx.font = '10px sans-serif';
  ctx.fillText(span >= 120 ? `-${(span / 60).toFixed(1)} min` : `-${span.toFixed(0)} s`, box.left, canvas.height - 5);
  ctx.fillText('now', box.right - 18, canvas.height - 5);
  return { ctx, box };
}

function drawLines(canvas, key, now) {
  const { ctx, box } = plotFrame(canvas, now);
  const names = [...new Set(plotHistory.flatMap((h) => Object.keys(h[key])))].sort();
  let top = 0;
  for (const h of plotHistory) for (const v of Object.values(h[key])) top = Math.max(top, v);
  top = top > 0 ? top * 1.1 : 1;
  const X = (t) => box.right - ((now - t) / plotSpan(now)) * (box.right - box.left);
  const Y = (v) => box.bottom - (v / top) * (box.bottom - box.top);
  ctx.fillStyle = '#5b6570';
  ctx.fillText(top.toPrecision(3), 2, box.top + 8);
  ctx.fillText('0', 2, box.bottom);
  const last = {};
  names.forEach((name, i) => {
    const colour = PLOT_COLOURS[i % PLOT_COLOURS.length];
    ctx.strokeStyle = colour; ctx.lineWidth = 1.5; ctx.beginPath();
    let drawing = false;
    for (const h of plotHistory) {
      const v = h[key][name];
      if (v == null) { drawing = false; continue; }
      if (drawing) ctx.lineTo(X(h.t), Y(v)); else ctx.moveTo(X(h.t), Y(v));
      drawing = true;
      last[name] = v;
    }
    ctx.stroke();
    ctx.fillStyle = colour;
    ctx.fillText(`${name} ${last[name] == null ? '-' : last[name].toFixed(1)}`, box.right + 6, box.top + 10 + i * 12);
  });
  if (!names.length) { ctx.fillStyle = '#5b6570'; ctx.fillText(key === 'rtt' ? 'no operator connected' : 'no data yet', box.left + 8, box.top + 20); }
  // The latest value of each series (the browser tests read it).
  canvas.dataset.series = JSON.stringify(last);
  canvas.dataset.samples = String(plotHistory.length);
}

function drawHolder(canvas, now) {
  const { ctx, box } = plotFrame(canvas, now);
  const holders = [...new Set(plotHistory.map((h) => h.holder))];
  const X = (t) => box.right - ((now - t) / plotSpan(now)) * (box.right - box.left);
  const row = Math.min(24, (box.bottom - box.top) / Math.max(1, holders.length));
  holders.forEach((name, i) => {
    const colour = name === 'STOP' ? '#c62828' : PLOT_COLOURS[i % PLOT_COLOURS.length];
    ctx.fillStyle = colour;
    ctx.fillText(name, box.right + 6, box.top + row * i + row / 2 + 4);
    plotHistory.forEach((h, k) => {
      if (h.holder !== name) return;
      const next = plotHistory[k + 1];
      const x0 = X(h.t), x1 = next ? X(next.t) : box.right;
      ctx.fillRect(x0, box.top + row * i + 2, Math.max(1, x1 - x0), row - 4);
    });
  });
  canvas.dataset.holders = JSON.stringify(holders);
  canvas.dataset.current = plotHistory.length ? plotHistory[plotHistory.length - 1].holder : '';
}

// The wiring's arrowheads (one per platform colour).
function wiringArrowheads(add) {
  const defs = add('defs', {});
  const ns = 'http://www.w3.org/2000/svg';
  for (const [id, colour] of [['arrow', '#567'], ['arrow-network', '#b36b00']]) {
    const marker = document.createElementNS(ns, 'marker');
    for (const [k, v] of Object.entries({ id, viewBox: '0 0 10 10', refX: '10', refY: '5', markerWidth: '8', markerHeight: '8', orient: 'auto-start-reverse' })) marker.setAttribute(k, v);
    const head = document.createElementNS(ns, 'path');
    head.setAttribute('d', 'M 0 0 L 10 5 L 0 10 z');
    head.setAttribute('fill', colour);
    marker.append(head);
    defs.append(marker);
  }
}

// The robot-file editor: validates as you type (EDITOR_DEBOUNCE_MS after
// the last key) with the host's own checks (POST .../validate/FILE: the
// diagnostics of `subsume check`), and stages exactly the text that
// validated.
const EDITOR_DEBOUNCE_MS = 400;
let editorTimer = null;
let editorValidated = null;
let editorSeq = 0;
function editorTarget() {
  return `/platforms/${$('editor-platform').value}/validate/${encodeURIComponent($('editor-name').value.trim())}`;
}
async function editorValidate() {
  const text = $('editor').value;
  const seqNow = ++editorSeq;
  const status = $('editor-status');
  status.className = '';
  status.textContent = 'validating...';
  $('editor-stage').disabled = true;
  let result, error;
  try { result = await api('POST', editorTarget(), text, { 'content-type': 'application/xml' }); } catch (err) { error = err; }
  if (seqNow !== editorSeq) return; // a newer validation is under way
  const list = $('editor-diagnostics');
  list.replaceChildren();
  if (error) {
    status.className = 'error';
    status.textContent = error.message;
    for (const d of (error.body && error.body.diagnostics) || []) {
      list.append(el('li', { 'data-line': String(d.line), 'data-column': String(d.column) }, `${d.line}:${d.column}: ${d.message}`));
    }
    editorValidated = null;
    return;
  }
  status.className = 'ok';
  status.textContent = `valid (${result.components} components, ${result.connections} connections; changes: ${result.changes.join(', ') || 'nothing'})`;
  editorValidated = { text, platform: $('editor-platform').value, name: $('editor-name').value.trim() };
  $('editor-stage').disabled = false;
}
function editorChanged() {
  clearTimeout(editorTimer);
  editorValidated = null;
  $('editor-stage').disabled = true;
  $('editor-status').className = '';
  $('editor-status').textContent = 'editing...';
  editorTimer = setTimeout(editorValidate, EDITOR_DEBOUNCE_MS);
}
$('editor').addEventListener('input', editorChanged);
$('editor-name').addEventListener('input', editorChanged);
$('editor-platform').addEventListener('change', editorChanged);
$('editor-load').addEventListener('click', async () => {
  try {
    const { sets } = await api('GET', '/sets');
    const active = sets.find((x) => x.status === 'active');
    if (!active) throw new Error('no active set');
    const { config, set } = await api('GET', `/sets/${active.id}`);
    $('editor').value = config;
    $('editor-name').value = set.config_name;
    editorChanged();
  } catch (err) {
    $('editor-status').className = 'error';
    $('editor-status').textContent = `could not load the active file: ${err.message}`;
  }
});
$('editor-stage').addEventListener('click', async () => {
  const staged = editorValidated;
  if (!staged || staged.text !== $('editor').value) return;
  try {
    const { set } = await api('PUT', `/platforms/${staged.platform}/configs/${encodeURIComponent(staged.name)}`, staged.text, { 'content-type': 'application/xml' });
    $('editor-status').className = 'ok';
    $('editor-status').textContent = `staged as set ${set.id} (changes: ${set.changes.join(', ') || 'nothing'})`;
    $('editor-stage').disabled = true;
    await refreshSets();
    showGraph(set.id);
  } catch (err) {
    $('editor-status').className = 'error';
    $('editor-status').textContent = `not staged: ${err.message}`;
  }
});

// The wiring's left-to-right order, with as few edges pointing back as the
// greedy rule of Eades, Lin and Smyth (1993) finds: components nothing
// feeds go first and those that feed nothing last; in a loop, the one
// that sends the most more than it receives goes first (the sensors'
// link, whose outputs feed the rest).
function flowOrder(names, edges) {
  const left = [];
  const right = [];
  const rest = new Set(names);
  const degree = (n, out) => edges.filter(([a, b]) => a !== b && rest.has(a) && rest.has(b) && (out ? a === n : b === n)).length;
  while (rest.size) {
    for (let changed = true; changed;) {
      changed = false;
      for (const n of [...rest]) if (degree(n, true) === 0 && degree(n, false) > 0) { right.unshift(n); rest.delete(n); changed = true; }
      for (const n of [...rest]) if (degree(n, false) === 0) { left.push(n); rest.delete(n); changed = true; }
    }
    let best = null;
    for (const n of rest) if (best === null || degree(n, true) - degree(n, false) > degree(best, true) - degree(best, false)) best = n;
    if (best !== null) { left.push(best); rest.delete(best); }
  }
  return new Map([...left, ...right].map((n, i) => [n, i]));
}

// ---- recordings (POST /recordings/start|stop; developers and admins) ------
function recordingStatus(text, className = '') {
  $('recording-status').className = className;
  $('recording-status').textContent = text;
}
async function refreshRecordings() {
  const body = $('recording-list').querySelector('tbody');
  try {
    const { recording, files } = await api('GET', '/recordings');
    $('recording-start').disabled = !!recording;
    $('recording-stop').disabled = !recording;
    if (recording) recordingStatus(`recording to ${recording.name} since ${new Date(recording.started_unix_ms).toLocaleTimeString()} (by ${recording.by}${recording.fresh_start ? ', from a fresh start' : ''})`);
    else if (!$('recording-status').dataset.kept) recordingStatus('not recording');
    body.replaceChildren(...files.slice().reverse().map((f) => {
      const link = el('a', { href: `/api/v1/recordings/${encodeURIComponent(f.name)}`, download: f.name }, f.name);
      const actions = el('td', {});
      if (!f.recording) {
        const remove = el('button', { class: 'delete', 'data-name': f.name }, 'delete');
        remove.addEventListener('click', async () => {
          if (!confirm(`Delete ${f.name}?`)) return;
          try { await api('DELETE', `/recordings/${encodeURIComponent(f.name)}`); } catch (err) { recordingStatus(err.message, 'error'); }
          refreshRecordings();
        });
        actions.append(remove);
      } else {
        actions.append('being written');
      }
      return el('tr', { 'data-name': f.name }, el('td', {}, link), el('td', { class: 'bytes' }, `${(f.bytes / 1024).toFixed(0)} KiB`),
        el('td', {}, new Date(f.modified_unix_ms).toLocaleString()), actions);
    }));
  } catch (err) {
    body.replaceChildren();
    $('recording-start').disabled = true;
    $('recording-stop').disabled = true;
    recordingStatus(err.message, 'error');
  }
}
$('recording-start').addEventListener('click', async () => {
  delete $('recording-status').dataset.kept;
  // From a fresh start: the host re-activates the running set and records
  // from its first call (every component starts inside the recording).
  const body = JSON.stringify({ fresh_start: $('recording-fresh').checked });
  try { await api('POST', '/recordings/start', body, { 'content-type': 'application/json' }); } catch (err) { recordingStatus(`not started: ${err.message}`, 'error'); $('recording-status').dataset.kept = '1'; }
  refreshRecordings();
});
$('recording-stop').addEventListener('click', async () => {
  try {
    const { stopped } = await api('POST', '/recordings/stop');
    recordingStatus(`stopped ${stopped.name}: ${stopped.messages} messages, ${(stopped.bytes / 1024).toFixed(0)} KiB in ${stopped.files.join(', ')}`, 'ok');
  } catch (err) {
    recordingStatus(`not stopped: ${err.message}`, 'error');
  }
  $('recording-status').dataset.kept = '1';
  refreshRecordings();
});

// ---- replay before activation (POST /sets/{id}/replay; developers and admins)
function replayButton(id) {
  const button = el('button', { class: 'replay', 'data-set': id, 'data-may': 'record', title: 'Replay this set against the chosen recording' }, 'replay');
  button.addEventListener('click', () => replaySet(id));
  return button;
}
async function refreshReplayRecordings() {
  const select = $('replay-recording');
  const kept = select.value;
  try {
    const { files } = await api('GET', '/recordings');
    select.replaceChildren(...files.filter((f) => !f.recording).reverse().map((f) => el('option', { value: f.name }, f.name)));
    if (files.some((f) => f.name === kept)) select.value = kept;
  } catch (err) {
    select.replaceChildren();
  }
}
// What one recorded call emitted on a port: nothing, a value, or a list.
function showReplayValue(values) {
  if (!values || values.length === 0) return 'nothing';
  return values.length === 1 ? JSON.stringify(values[0]) : JSON.stringify(values);
}
async function replaySet(id) {
  const result = $('replay-result');
  const table = $('replay-divergences');
  const recording = $('replay-recording').value;
  table.hidden = true;
  if (!recording) {
    result.className = 'error';
    result.textContent = 'no recording to replay against: record one in the Recordings tab';
    return;
  }
  const only = $('replay-only').value.split(/[\s,]+/).filter((c) => c);
  result.className = '';
  result.textContent = `replaying set ${id} against ${recording}...`;
  for (const b of document.querySelectorAll('button.replay')) b.disabled = true;
  try {
    const body = JSON.stringify({ recording, only });
    const { identical, report } = await api('POST', `/sets/${id}/replay`, body, { 'content-type': 'application/json' });
    const what = `set ${id} against ${recording} (${report.components.join(', ')}; ${report.compared} outputs compared over ${report.recorded_s.toFixed(1)} recorded s)`;
    result.dataset.identical = String(identical);
    if (identical) {
      result.className = 'ok';
      result.textContent = `identical: ${what}`;
    } else {
      const first = report.divergences[0];
      result.className = 'error';
      result.textContent = `diverges: ${what}; first: ${first.component}.${first.port} at ${first.time_s.toFixed(6)} s (call ${first.call}: ${first.call_kind}): recorded ${showReplayValue(first.recorded)}, new ${showReplayValue(first.replayed)}`;
      table.querySelector('tbody').replaceChildren(...report.divergences.map((d) => el('tr', { 'data-port': `${d.component}.${d.port}` },
        el('td', {}, d.time_s.toFixed(6)), el('td', {}, `${d.component}.${d.port}`), el('td', {}, `${d.call}: ${d.call_kind}`),
        el('td', { class: 'recorded' }, showReplayValue(d.recorded)), el('td', { class: 'replayed' }, showReplayValue(d.replayed)), el('td', {}, String(d.calls_differing)))));
      table.hidden = false;
    }
  } catch (err) {
    delete result.dataset.identical;
    result.className = 'error';
    result.textContent = `set ${id} was not replayed: ${err.message}`;
  }
  for (const b of document.querySelectorAll('button.replay')) b.disabled = false;
}

// ---- worlds for the simulated robot (docs/portal.md) ----------------------
async function refreshWorlds() {
  try {
    const { worlds } = await api('GET', '/worlds');
    $('world-list').textContent = worlds.map((w) => `${w.name} (${w.size} bytes, by ${w.uploaded_by})`).join(', ') || 'none yet';
  } catch (err) {
    $('world-list').textContent = err.message;
  }
}
$('world-upload').addEventListener('click', async () => {
  const file = $('world-file').files[0];
  $('world-errors').replaceChildren();
  $('world-result').textContent = '';
  if (!file) { $('world-result').textContent = 'choose a world file first'; return; }
  try {
    const { world } = await api('PUT', `/worlds/${encodeURIComponent(file.name)}`, await file.text(), { 'content-type': 'text/plain' });
    $('world-result').className = 'ok';
    $('world-result').textContent = `stored ${world.name} (sha256 ${world.sha256.slice(0, 12)}...)`;
  } catch (err) {
    showRefusal(err, 'world-result', 'world-errors');
  }
  refreshWorlds();
});

// ---- the remote lab (docs/lab.md) ------------------------------------------
// Experiments: submit a staged set (or a robot file, staged first), watch
// each one's states live (GET /lab/events: an event `lab` with the lab and
// the caller's experiments at every change), cancel, download results;
// reservations; for admins the queue, the baseline and the settings. While
// an experiment runs, a banner on every tab says who runs which set and
// how long is left, with a stop button for its submitter and admins.
let lab = null;
let labExperiments = [];
let labEvents = null;
// The host's clock minus this page's (the lab view carries the host's), so
// countdowns are right on a page whose clock is off.
let hostOffsetMs = 0;
const hostNow = () => Date.now() + hostOffsetMs;
const FINAL_STATES = new Set(['done', 'refused', 'cancelled', 'aborted', 'failed']);
// Experiments drawn at most (an admin's list can hold thousands).
const MAX_EXPERIMENTS_SHOWN = 100;
const openDetails = new Set();

// "41 s", "3 min 20 s", "2 h 5 min".
function span(seconds) {
  const s = Math.max(0, Math.round(seconds));
  if (s < 90) return `${s} s`;
  if (s < 5400) return `${Math.floor(s / 60)} min${s % 60 ? ` ${s % 60} s` : ''}`;
  const m = Math.round(s / 60);
  return `${Math.floor(m / 60)} h ${m % 60} min`;
}
const clock = (ms) => new Date(ms).toLocaleTimeString();
const when = (ms) => new Date(ms).toLocaleString();
// A time left until `atMs` (the host's clock) that the ticker keeps current.
const countdown = (atMs) => el('span', { class: 'countdown', 'data-until': String(atMs) }, span((atMs - hostNow()) / 1000));
function tick() {
  for (const node of document.querySelectorAll('[data-until]')) node.textContent = span((Number(node.dataset.until) - hostNow()) / 1000);
}
setInterval(tick, 1000);

function startLab() {
  const start = new Date(Date.now() + 10 * 60000);
  start.setMinutes(Math.ceil(start.getMinutes() / 5) * 5, 0, 0);
  const local = new Date(start.getTime() - start.getTimezoneOffset() * 60000);
  $('lab-book-start').value = local.toISOString().slice(0, 16);
  buildSettingsForm();
  refreshLabSets();
  if (labEvents) labEvents.close();
  labEvents = new EventSource('/api/v1/lab/events');
  labEvents.addEventListener('lab', (e) => {
    const data = JSON.parse(e.data);
    lab = data.lab;
    labExperiments = data.experiments;
    hostOffsetMs = lab.now_unix_ms - Date.now();
    applyRoles(lab.reserved_now);
    renderBanner();
    renderLab();
  });
}

// The banner on every tab while an experiment runs.
function renderBanner() {
  const running = lab && lab.running;
  const banner = $('lab-banner');
  banner.hidden = !running;
  document.body.classList.toggle('experiment-running', !!running);
  if (!running) { delete banner.dataset.experiment; return; }
  banner.dataset.experiment = String(running.id);
  const label = running.label ? ` '${running.label}'` : '';
  $('lab-banner-text').replaceChildren(
    el('b', {}, `Experiment ${running.id}${label}`), ` by ${running.submitter} runs set ${running.set}: `,
    countdown(running.ends_unix_ms), ' left');
  $('lab-banner-stop').hidden = !(me && (running.submitter === me.name || may('admin')));
}
$('lab-banner-watch').addEventListener('click', () => showTab('lab'));
$('lab-banner-stop').addEventListener('click', async () => {
  const id = $('lab-banner').dataset.experiment;
  if (!id) return;
  $('lab-banner-stop').disabled = true;
  $('lab-banner-text').textContent = `stopping experiment ${id}: the robot goes back to the baseline...`;
  try { await api('POST', `/experiments/${id}/cancel`); } catch (err) { $('lab-banner-text').textContent = `not stopped: ${err.message}`; }
  $('lab-banner-stop').disabled = false;
});
for (const link of document.querySelectorAll('a[data-goto]')) {
  link.addEventListener('click', (e) => { e.preventDefault(); showTab(link.dataset.goto); });
}

// The staged sets to submit (the user's own first) and, for admins, to
// mark as the baseline.
async function refreshLabSets() {
  let sets;
  try { ({ sets } = await api('GET', '/sets')); } catch (err) { return; }
  const mine = (x) => (me && x.created_by === me.name ? 0 : 1);
  const ordered = sets.slice().sort((a, b) => mine(a) - mine(b) || b.id - a.id);
  const option = (x) => el('option', { value: String(x.id) }, `set ${x.id}: ${x.config_name} (by ${x.created_by}, ${x.status})`);
  // A choice the user made stays chosen; otherwise her newest own set, or
  // the lab's baseline; never someone else's staged set (an admin sees
  // every user's).
  const pick = $('lab-set');
  const kept = pick.dataset.chosen;
  const own = ordered.find((x) => mine(x) === 0);
  const baseline = lab ? ordered.find((x) => x.id === lab.baseline) : undefined;
  const fallback = own || baseline;
  const placeholder = fallback ? [] : [el('option', { value: '' }, '(choose a set)')];
  pick.replaceChildren(...placeholder, ...ordered.map(option));
  if (ordered.some((x) => String(x.id) === kept)) pick.value = kept;
  else pick.value = fallback ? String(fallback.id) : '';
  const base = $('lab-baseline-set');
  const keptBase = base.dataset.chosen || String(lab ? lab.baseline : '');
  base.replaceChildren(...sets.slice().sort((a, b) => b.id - a.id).map(option));
  if (ordered.some((x) => String(x.id) === keptBase)) base.value = keptBase;
}
for (const id of ['lab-set', 'lab-baseline-set']) $(id).addEventListener('change', () => { $(id).dataset.chosen = $(id).value; });

// A refused request's answer on `resultId`: the reason, each located
// diagnostic (file:line:column: message) in `errorsId`, and, for a 429,
// when the limit frees.
function showLabRefusal(err, what, resultId, errorsId) {
  const result = $(resultId);
  result.className = 'error';
  result.dataset.status = String(err.status || '');
  result.replaceChildren(`${what}${err.status ? ` (${err.status})` : ''}: ${err.message}`);
  if (err.status === 429 && err.retryAfter) {
    const at = hostNow() + Number(err.retryAfter) * 1000;
    result.append(el('span', { class: 'frees' }, ` You may submit again at ${when(at)} (in `, countdown(at), ').'));
  }
  if (errorsId) {
    $(errorsId).replaceChildren(...((err.body && err.body.diagnostics) || []).map((d) =>
      el('li', { 'data-line': String(d.line), 'data-column': String(d.column) }, d.text)));
  }
}

$('lab-submit-form').addEventListener('submit', async (e) => {
  e.preventDefault();
  const result = $('lab-submit-result');
  result.className = '';
  delete result.dataset.experiment;
  $('lab-submit-errors').replaceChildren();
  const file = $('lab-robot').files[0];
  let set = Number($('lab-set').value);
  let staged = '';
  if (file) {
    result.textContent = `validating and staging ${file.name}...`;
    try {
      const platform = $('lab-platform').value;
      const answer = await api('PUT', `/platforms/${platform}/configs/${encodeURIComponent(file.name)}`, await file.text(), { 'content-type': 'application/xml' });
      set = answer.set.id;
      staged = `staged ${file.name} as set ${set}; `;
      $('lab-robot').value = '';
      refreshLabSets();
    } catch (err) {
      showLabRefusal(err, `${file.name} was not staged, nothing was submitted`, 'lab-submit-result', 'lab-submit-errors');
      return;
    }
  }
  if (!set) { result.className = 'error'; result.textContent = 'choose a staged set or a robot file'; return; }
  result.textContent = `${staged}submitting set ${set}...`;
  try {
    const body = JSON.stringify({ set, duration_s: Number($('lab-duration').value), label: $('lab-label').value });
    const { experiment } = await api('POST', '/experiments', body, { 'content-type': 'application/json' });
    result.className = 'ok';
    result.dataset.experiment = String(experiment.id);
    result.textContent = `${staged}submitted set ${set} as experiment ${experiment.id}: it runs in the simulator first`;
  } catch (err) {
    showLabRefusal(err, `${staged}set ${set} was not submitted`, 'lab-submit-result', 'lab-submit-errors');
  }
});

function renderLab() {
  if (!lab || $('tab-lab').hidden) return;
  const state = [`The queue ${lab.paused ? 'is paused by an admin' : 'runs'}; ${lab.queued} queued; the baseline is set ${lab.baseline}.`];
  if (lab.held) state.push(` It waits: ${lab.held}.`);
  if (lab.reserved_now) state.push(` Reserved now for ${lab.reserved_now.user} until ${clock(lab.reserved_now.end_ms)}.`);
  $('lab-state').textContent = state.join('');
  $('lab-state').dataset.paused = String(lab.paused);
  $('lab-reset-wait').hidden = lab.awaiting_reset == null;
  $('lab-reset-text').textContent = lab.awaiting_reset == null ? '' : `Experiment ${lab.awaiting_reset} is next and waits for the robot to be put back at its start.`;
  const running = lab.running;
  $('lab-live').hidden = !running;
  if (running) {
    $('lab-live-title').textContent = `On the robot now: experiment ${running.id} by ${running.submitter} (set ${running.set}${running.label ? `, '${running.label}'` : ''})`;
    $('lab-live-left').replaceChildren(countdown(running.ends_unix_ms), ` (until ${clock(running.ends_unix_ms)})`);
  }
  $('lab-experiments-title').textContent = me && may('admin') ? 'Every experiment' : 'My experiments';
  const shown = labExperiments.slice(0, MAX_EXPERIMENTS_SHOWN).map(experimentCard);
  if (!labExperiments.length) shown.push(el('p', { class: 'hint' }, 'none yet'));
  if (labExperiments.length > MAX_EXPERIMENTS_SHOWN) shown.push(el('p', { class: 'hint' }, `and ${labExperiments.length - MAX_EXPERIMENTS_SHOWN} older ones`));
  $('lab-experiments').replaceChildren(...shown);
  applyRole($('lab-experiments'));
  renderBoard();
  renderReservations();
  renderLabAdmin();
}

// The owner's task's leaderboard (GET /api/v1/tasks/NAME/leaderboard):
// fetched again when the lab changes, one request at a time.
let boardFetching = false;
let boardAgain = false;
const number = (v) => (v == null ? '-' : String(Math.round(v * 1000) / 1000));
async function renderBoard() {
  const task = lab && lab.task;
  $('lab-board').hidden = !task;
  if (!task) return;
  if (boardFetching) { boardAgain = true; return; }
  boardFetching = true;
  try {
    const { leaderboard: board } = await api('GET', `/tasks/${encodeURIComponent(task.name)}/leaderboard`);
    $('lab-board-title').textContent = `Leaderboard: ${board.task}`;
    $('lab-board-task').textContent = `${board.description ? board.description + '. ' : ''}Ranked by ${board.metric} (${board.better} is better), each user's ${board.board} run that ended done.`;
    const rows = board.entries.map((e) => el('tr', { 'data-rank': e.rank == null ? '' : String(e.rank), class: e.yours ? 'yours' : '' },
      el('td', { class: 'rank' }, e.rank == null ? '-' : String(e.rank)),
      el('td', { class: 'user' }, e.user + (e.experiment != null ? ` (experiment ${e.experiment})` : '')),
      el('td', { class: 'value' }, number(e.value)),
      el('td', { class: 'preflight-value' }, number(e.preflight_value)),
      el('td', { class: 'gap' }, number(e.gap)),
      el('td', {}, when(e.ended_ms)),
      el('td', { class: 'sha', title: e.recording_sha256 }, e.recording_sha256.slice(0, 12))));
    $('lab-board-table').querySelector('tbody').replaceChildren(...rows);
    $('lab-board-said').textContent = rows.length ? '' : 'no scored run yet';
  } catch (err) {
    $('lab-board-said').textContent = `the leaderboard did not load: ${err.message}`;
  } finally {
    boardFetching = false;
    if (boardAgain) { boardAgain = false; renderBoard(); }
  }
}

// Where an experiment is now, in words.
function experimentNow(x) {
  const now = el('div', { class: 'exp-now' });
  if (x.state === 'checking') now.append('its set is validated again');
  if (x.state === 'preflight') now.append('it runs in the simulator first (the preflight)');
  if (x.state === 'finishing') now.append('the baseline comes back and its results are written');
  if (x.state === 'running' && x.ends_unix_ms) now.append('on the robot: ', countdown(x.ends_unix_ms), ` left (until ${clock(x.ends_unix_ms)})`);
  if (x.state === 'queued') {
    now.append(el('span', { class: 'place' }, `place ${x.place || '?'} in the queue`), '; ');
    if (x.awaiting_reset) now.append('it is next and waits for the robot to be reset (an admin confirms)');
    else if (x.eta_unix_ms) now.append(el('span', { class: 'eta', 'data-eta': String(x.eta_unix_ms) }, `starts about ${clock(x.eta_unix_ms)} (in `, countdown(x.eta_unix_ms), ')'));
    else now.append(lab.paused ? 'the queue is paused' : (lab.held || 'no start time known yet'));
  }
  return now;
}


// How the algorithm did, apart from the run's status (done says it ran to
// its end): the same words as `subsume lab show` (RunOutcome::said).
function outcomeText(o) {
  const parts = [];
  if (o.ended_by) parts.push(`ended: ${o.ended_by}`);
  if (o.goal_reached === true) parts.push('goal reached');
  if (o.goal_reached === false) parts.push('goal not reached');
  parts.push(o.collisions === 0 ? 'no collision' : o.collisions === 1 ? '1 collision' : `${o.collisions} collisions`);
  const at = (f) => (f.at_s == null ? '' : ` at ${f.at_s.toFixed(1)} s`);
  if (o.faults.length === 0) parts.push('no fault');
  else if (o.faults.length === 1) parts.push(`component '${o.faults[0].component}' faulted${at(o.faults[0])}: ${o.faults[0].reason}`);
  else parts.push(`${o.faults.length} faults (first: '${o.faults[0].component}'${at(o.faults[0])}: ${o.faults[0].reason})`);
  const kinds = Object.entries(o.interventions);
  parts.push(kinds.length === 0 ? 'no intervention' : `interventions: ${kinds.map(([c, n]) => `${c} ${n}`).join(', ')}`);
  return parts.join(', ');
}
function experimentCard(x) {
  const card = el('div', { class: `experiment state-${x.state}`, 'data-experiment': String(x.id), 'data-state': x.state });
  const actions = el('span', { class: 'exp-actions' });
  if (!FINAL_STATES.has(x.state)) {
    const cancel = el('button', { class: 'cancel', 'data-experiment': String(x.id) }, 'Cancel');
    cancel.addEventListener('click', async () => {
      cancel.disabled = true;
      try { await api('POST', `/experiments/${x.id}/cancel`); } catch (err) { card.append(el('p', { class: 'error' }, `not cancelled: ${err.message}`)); }
    });
    actions.append(cancel);
  } else if (x.results.length) {
    const bytes = x.results.reduce((sum, f) => sum + f.bytes, 0);
    actions.append(el('a', { class: 'results', href: `/api/v1/experiments/${x.id}/results`, download: `experiment-${x.id}.tar` },
      `Results (tar, ${x.results.length} files, ${(bytes / 1048576).toFixed(1)} MiB)`));
  }
  card.append(el('div', { class: 'exp-head' },
    el('b', {}, `Experiment ${x.id}`), ' ', el('span', { class: 'exp-label' }, x.label || '(no label)'), ' ',
    el('span', { class: 'state' }, x.state), actions));
  card.append(el('div', { class: 'exp-meta hint' }, `set ${x.set}, ${x.duration_s} s`,
    el('span', { class: 'lab-submitter', 'data-may': 'admin' }, `, by ${x.submitter}`), `, submitted ${when(x.submitted_ms)}`));
  if (!FINAL_STATES.has(x.state)) card.append(experimentNow(x));
  card.append(el('ol', { class: 'timeline' }, ...x.history.map((h) =>
    el('li', { 'data-state': h.state, title: h.cause }, el('span', { class: 'tl-state' }, h.state), ` ${clock(h.at_ms)}`))));
  if (x.reasons.length) card.append(el('ul', { class: 'reasons errors' }, ...x.reasons.map((r) => el('li', {}, r))));
  const p = x.preflight;
  if (p) {
    card.append(el('div', { class: 'preflight', 'data-passed': String(p.passed) },
      `Preflight: ${p.passed ? 'passed' : 'did not pass'} (${p.simulated_s.toFixed(1)} s simulated in ${p.wall_s.toFixed(1)} s)`,
      p.replay ? `; replay against the reference: ${JSON.stringify(p.replay)}` : ''));
  }
  if (x.run) {
    card.append(el('div', { class: 'run' }, `On the robot: ${x.run.ran_s.toFixed(1)} s; ${x.run.late_cycles} control cycles late ` +
      `beyond the watchdog's margin (worst ${x.run.worst_lateness_ms.toFixed(1)} ms)`));
    if (x.run.outcome) card.append(el('div', { class: 'outcome' }, `Outcome: ${outcomeText(x.run.outcome)}`));
  }
  if (x.score) {
    const simulated = x.preflight && x.preflight.score ? ` (the preflight's: ${number(x.preflight.score.value)})` : '';
    card.append(el('div', { class: 'score' }, `Score: task ${x.score.task}: ${x.score.metric} = ${number(x.score.value)}${simulated}`));
    // A scoring component's: which bytes scored it, its own sub-scores and
    // the built-in metrics beside them; a built-in metric's: its sub-scores.
    if (x.score.scorer_sha256) {
      card.append(el('div', { class: 'scorer', title: x.score.scorer_sha256 },
        `scored by the task's scoring component, sha256 ${x.score.scorer_sha256.slice(0, 12)}`));
    }
    const listed = (scores) => Object.entries(scores || {}).map(([name, v]) => `${name} ${number(v)}`).join(', ');
    if (Object.keys(x.score.sub_scores || {}).length) card.append(el('div', { class: 'sub-scores' }, `Sub-scores: ${listed(x.score.sub_scores)}`));
    if (Object.keys(x.score.built_in || {}).length) card.append(el('div', { class: 'built-in' }, `Built-in metrics: ${listed(x.score.built_in)}`));
  }
  if (x.reset) {
    const at = (p) => (p ? `(${p.x.toFixed(2)}, ${p.y.toFixed(2)}, ${p.heading.toFixed(2)} rad)` : 'no pose');
    card.append(el('div', { class: 'reset', 'data-passed': String(x.reset.passed) }, x.reset.passed
      ? `Reset by driving: back in ${x.reset.took_s.toFixed(1)} s from ${at(x.reset.from)} to ${at(x.reset.pose)}`
      : `Reset by driving failed after ${x.reset.took_s.toFixed(1)} s: ${x.reset.error}`));
  }
  if (x.recording_expired) card.append(el('p', { class: 'hint' }, "its recordings expired (the lab's retention cap); the record stays"));
  const details = el('details', {}, el('summary', {}, 'States with their causes, components'),
    el('table', { class: 'history' }, ...x.history.map((h) => el('tr', {}, el('td', {}, when(h.at_ms)), el('td', {}, h.state), el('td', {}, h.cause)))),
    el('table', { class: 'hashes' }, ...x.components.map((c) => el('tr', {}, el('td', {}, c.name), el('td', {}, c.source), el('td', { class: 'sha' }, c.sha256 || '')))));
  details.open = openDetails.has(x.id);
  details.addEventListener('toggle', () => (details.open ? openDetails.add(x.id) : openDetails.delete(x.id)));
  card.append(details);
  return card;
}

function renderReservations() {
  const body = $('lab-reservations').querySelector('tbody');
  body.replaceChildren(...lab.reservations.map((r) => {
    const actions = el('td', {});
    if (me && (r.user === me.name || may('admin'))) {
      const cancel = el('button', { class: 'unbook', 'data-reservation': String(r.id) }, 'Cancel');
      cancel.addEventListener('click', async () => {
        try { await api('DELETE', `/lab/reservations/${r.id}`); $('lab-book-result').textContent = `cancelled reservation ${r.id}`; } catch (err) { showLabRefusal(err, 'not cancelled', 'lab-book-result'); }
      });
      actions.append(cancel);
    }
    const now = lab.reserved_now && lab.reserved_now.id === r.id;
    return el('tr', { 'data-reservation': String(r.id), class: now ? 'now' : '' }, el('td', {}, String(r.id)), el('td', {}, r.user + (now ? ' (now)' : '')),
      el('td', {}, when(r.start_ms)), el('td', {}, when(r.end_ms)), actions);
  }));
  if (!lab.reservations.length) body.append(el('tr', {}, el('td', { colspan: '5', class: 'hint' }, 'none booked')));
}
$('lab-book').addEventListener('click', async () => {
  const start = new Date($('lab-book-start').value).getTime();
  const minutes = Number($('lab-book-minutes').value);
  if (!Number.isFinite(start)) { $('lab-book-result').className = 'error'; $('lab-book-result').textContent = 'choose when it starts'; return; }
  const request = { start_unix_ms: start, end_unix_ms: start + Math.round(minutes * 60000) };
  if ($('lab-book-for').value.trim()) request.user = $('lab-book-for').value.trim();
  try {
    const { reservation } = await api('POST', '/lab/reservations', JSON.stringify(request), { 'content-type': 'application/json' });
    $('lab-book-result').className = 'ok';
    $('lab-book-result').textContent = `booked reservation ${reservation.id} for ${reservation.user}: ${when(reservation.start_ms)} to ${clock(reservation.end_ms)}`;
  } catch (err) {
    showLabRefusal(err, 'not booked', 'lab-book-result');
  }
});

// ---- the lab for admins: the queue, the baseline, the owner's settings ----
// The settings form, one row per field: [path in the settings, label, kind].
const LAB_SETTINGS_FIELDS = [
  ['max_duration_s', 'Longest experiment (s)', 'number'],
  ['limits.max_queued', 'Experiments waiting, per user', 'number'],
  ['limits.robot_minutes_per_day', 'Robot minutes per user in any 24 h', 'number'],
  ['limits.max_reservation_s', 'Longest reservation (s)', 'number'],
  ['limits.reservation_per_day_s', 'Reserved seconds per user a day', 'number'],
  ['criteria.max_collisions', 'Preflight: collisions allowed', 'number'],
  ['criteria.allow_faults', 'Preflight: a component may fault', 'boolean'],
  ['criteria.allow_geofence', 'Preflight: the geofence may hold the robot', 'boolean'],
  ['criteria.allow_stop_zone', "Preflight: the envelope's stop zone may stop it", 'boolean'],
  ['criteria.end_run_on_breach', 'On the robot too: a run that breaks these criteria ends early', 'boolean'],
  ['stuck_after_min_s', 'A queued experiment never started is refused after (s, at least; or twice its first ETA)', 'number'],
  ['reset', 'Before each experiment the robot is reset by', ['sim', 'manual', 'drive']],
  ['preflight_world', "Preflight world (an uploaded world; empty: each set's own)", 'optional'],
  ['reference_recording', 'Reference recording to replay against (empty: none)', 'optional'],
  ['retention_bytes', 'Results kept, at most (MiB)', 'mebibytes'],
  ['kit', 'Researchers may download the lab kit', 'boolean'],
  ['preflight_timing.runs', 'Preflight runs (run 1 unperturbed, each later one with seeded timing)', 'number'],
  ['preflight_timing.tick_phase', "Preflight: seed each component's tick phase", 'boolean'],
  ['preflight_timing.sensor_latency_ms', 'Preflight: most sensor latency (ms)', 'number'],
  ['preflight_timing.range_noise_m', 'Preflight: most range noise (m)', 'number'],
  ['preflight_timing.serial_delay_ms', 'Preflight: most serial delay (ms)', 'number'],
];
let settingsDirty = false;
const settingId = (path) => 'lab-setting-' + path.replace(/[._]/g, '-');
function buildSettingsForm() {
  const fields = $('lab-settings-fields');
  if (fields.children.length) return;
  for (const [path, label, kind] of LAB_SETTINGS_FIELDS) {
    let input;
    if (Array.isArray(kind)) input = el('select', { id: settingId(path) }, ...kind.map((k) => el('option', { value: k }, k)));
    else if (kind === 'boolean') input = el('input', { id: settingId(path), type: 'checkbox' });
    else if (kind === 'optional') input = el('input', { id: settingId(path), size: '20' });
    else input = el('input', { id: settingId(path), type: 'number', step: 'any', min: '0' });
    input.addEventListener('input', () => { settingsDirty = true; });
    fields.append(el('label', { for: settingId(path) }, label), input);
  }
}
const settingAt = (settings, path) => path.split('.').reduce((o, k) => o[k], settings);
function fillSettings(settings) {
  for (const [path, , kind] of LAB_SETTINGS_FIELDS) {
    const input = $(settingId(path));
    const value = settingAt(settings, path);
    if (kind === 'boolean') input.checked = value;
    else if (kind === 'optional') input.value = value || '';
    else if (kind === 'mebibytes') input.value = String(value / 1048576);
    else input.value = String(value);
  }
  settingsDirty = false;
}
function readSettings() {
  const settings = JSON.parse(JSON.stringify(lab.settings));
  for (const [path, , kind] of LAB_SETTINGS_FIELDS) {
    const input = $(settingId(path));
    let value = input.value;
    if (kind === 'boolean') value = input.checked;
    else if (kind === 'optional') value = value.trim() || null;
    else if (kind === 'mebibytes') value = Math.round(Number(value) * 1048576);
    else if (kind === 'number') value = Number(value);
    const keys = path.split('.');
    const last = keys.pop();
    keys.reduce((o, k) => o[k], settings)[last] = value;
  }
  return settings;
}
function renderLabAdmin() {
  if (!me || !may('admin') || !lab.settings) return;
  $('lab-queue-state').textContent = lab.paused ? 'paused' : 'runs';
  $('lab-pause').disabled = lab.paused;
  $('lab-resume').disabled = !lab.paused;
  $('lab-baseline').textContent = `set ${lab.baseline}`;
  if (!settingsDirty) fillSettings(lab.settings);
}
for (const [id, action] of [['lab-pause', 'pause'], ['lab-resume', 'resume']]) {
  $(id).addEventListener('click', async () => {
    try {
      const { paused } = await api('POST', `/lab/${action}`);
      $('lab-queue-result').className = 'ok';
      $('lab-queue-result').textContent = paused ? 'paused: nothing new starts; what runs goes on' : 'resumed';
    } catch (err) {
      showLabRefusal(err, `not ${action}d`, 'lab-queue-result');
    }
  });
}
$('lab-baseline-mark').addEventListener('click', async () => {
  const set = Number($('lab-baseline-set').value);
  try {
    const { baseline } = await api('PUT', '/lab/baseline', JSON.stringify({ set }), { 'content-type': 'application/json' });
    $('lab-baseline-result').className = 'ok';
    $('lab-baseline-result').textContent = `set ${baseline} is the baseline: the robot runs it between experiments`;
  } catch (err) {
    showLabRefusal(err, `set ${set} is not the baseline`, 'lab-baseline-result');
  }
});
$('lab-settings').addEventListener('submit', async (e) => {
  e.preventDefault();
  try {
    const { settings } = await api('PUT', '/lab/settings', JSON.stringify(readSettings()), { 'content-type': 'application/json' });
    fillSettings(settings);
    $('lab-settings-result').className = 'ok';
    $('lab-settings-result').textContent = 'saved: they apply to experiments submitted from now on';
  } catch (err) {
    showLabRefusal(err, 'not saved', 'lab-settings-result');
  }
});
$('lab-reset-confirm').addEventListener('click', async () => {
  try {
    const { confirmed_for: id } = await api('POST', '/lab/reset');
    $('lab-reset-text').textContent = `confirmed: experiment ${id} starts`;
  } catch (err) {
    $('lab-reset-text').textContent = `not confirmed: ${err.message}`;
  }
});

// The live view of the experiment on the robot, in the Lab tab (called
// with every live status).
function labOnStatus(s) {
  if ($('tab-lab').hidden || !lab || !lab.running) return;
  drawMap(s.sim, s.envelope, $('lab-map'));
  const arbiter = s.arbiter || {};
  $('lab-live-holder').textContent = arbiter.holder || 'nobody (STOP)';
  $('lab-live-pose').textContent = s.sim ? `x ${s.sim.x.toFixed(2)} y ${s.sim.y.toFixed(2)} heading ${s.sim.heading.toFixed(2)}` : '-';
  $('lab-live-collisions').textContent = s.sim ? String(s.sim.collisions) : '-';
  $('lab-live-envelope').textContent = s.envelope
    ? `passed ${s.envelope.passed}, scaled ${s.envelope.scaled}, stopped ${s.envelope.stopped}${s.envelope.last ? `; last: ${s.envelope.last.text}` : ''}`
    : 'none';
  const sha = (s.experiment && s.experiment.sha256) || {};
  $('lab-live-components').textContent = s.components
    .map((c) => `${c.name}: ${c.state}${c.fault ? ' (' + c.fault + ')' : ''}${sha[c.name] ? ', sha256 ' + sha[c.name].slice(0, 12) : ''}`).join('\n');
}
