// The operator dashboard: live skeleton, topology, bones, coverage hints, residual plot with slip
// markers, tracker status and session controls. It only shows what the service publishes on
// /ws/live (status, fit, residuals, events, pose) and calls the REST API for session control.

import { api, ApiError, connectLive, download, foundOn, jointName, readable, SkeletonView } from './common.js';

const $ = (id) => document.getElementById(id);
const view = new SkeletonView($('view'));
const WINDOW_S = 60;
const PLOT_HEIGHT = 260;

const state = {
  session: null,        // live session summary from the status messages
  lastSessionId: null,  // newest session (live or stopped): what the download buttons fetch
  lastPerformer: '',
  fit: null,
  progress: null,       // the service's progress of the fit shown (docs/service.md, Progress): the page computes none
  trackerConnected: null,
  rate: [],             // [wall seconds, frames] samples for the measured frame rate
  conflicts: new Set(), // name conflicts already alerted in this session (fits repeat them ~15 times a second)
};

// ---------------------------------------------------------------------------------- tracker status

function setPill(el, text, kind, dataState) {
  el.textContent = text;
  el.className = `pill pill-${kind}`;
  if (dataState) el.dataset.state = dataState;
}

function fmtInt(n) { return n === undefined || n === null ? '–' : Number(n).toLocaleString('en-GB'); }

// Frames per second over the last few seconds, timed by the server's clock (message "time"), so
// bursts in delivery do not show as rate swings.
function measuredRate(frames, now) {
  state.rate.push([now, frames]);
  while (state.rate.length > 2 && now - state.rate[0][0] > 3) state.rate.shift();
  const [t0, f0] = state.rate[0];
  return now - t0 > 0.8 ? (frames - f0) / (now - t0) : null;
}

function showStatus(s, serverTime) {
  const connected = !!s.connected;
  setPill($('tracker'), connected ? 'tracker connected' : 'tracker disconnected', connected ? 'ok' : 'bad',
    connected ? 'connected' : 'disconnected');
  const rate = serverTime ? measuredRate(s.frames || 0, serverTime) : null;
  $('fig-rate').textContent = connected && rate !== null ? `${rate.toFixed(0)} Hz` : (connected ? '…' : '0 Hz');
  $('fig-rate').title = s.rate_hz ? `tracker set to ${s.rate_hz} Hz` : '';
  $('fig-birds').textContent = fmtInt(s.birds);
  $('fig-frames').textContent = fmtInt(s.frames);
  $('fig-dropped').textContent = fmtInt(s.dropped_records);
  $('fig-dropped').classList.toggle('warn', (s.dropped_records || 0) > 0);
  $('fig-resynced').textContent = fmtInt(s.resynced);
  $('fig-reconnects').textContent = fmtInt(s.reconnects);
  const banner = $('banner');
  if (!connected) {
    const why = s.last_error ? ` (${s.last_error})` : '';
    banner.textContent = `Tracker disconnected${why} — flockcal keeps trying to reconnect; the session keeps what it has.`;
    banner.classList.remove('hidden');
  } else {
    banner.classList.add('hidden');
  }
  state.trackerConnected = connected;
  setSession(s.session || null);
}

function showLink(st) {
  const text = { open: 'server live', connecting: 'server: connecting…', closed: 'server: reconnecting…',
    unauthorised: 'server: token refused' }[st];
  setPill($('link'), text, st === 'open' ? 'ok' : (st === 'unauthorised' ? 'bad' : 'warn'), st);
  const b = $('link-banner');
  if (st === 'open' || st === 'connecting') { b.classList.add('hidden'); return; }
  b.textContent = st === 'unauthorised'
    ? 'This service needs a token: open the dashboard as /?token=YOUR_TOKEN.'
    : 'Lost the connection to the flockcal service — reconnecting by itself…';
  b.classList.remove('hidden');
}

// ---------------------------------------------------------------------------------- session

function fmtDuration(s) {
  if (!Number.isFinite(s)) return '–';
  const m = Math.floor(s / 60);
  return `${m}:${String(Math.floor(s % 60)).padStart(2, '0')}`;
}

function setSession(session) {
  const prev = state.session;
  if (session && (!prev || prev.id !== session.id)) {
    // A new session (from here, the kiosk or the API): start its plots afresh, with what it already has.
    resetSessionViews();
    state.lastSessionId = session.id;
    state.lastPerformer = session.performer;
    backfill(session);
  }
  state.session = session;
  if (prev && !session) showStopped(prev);
  $('start').disabled = !!session;
  $('stop').disabled = !session;
  $('performer').disabled = !!session;
  $('hierarchy').disabled = !!session;
  const pill = $('session-state');
  if (session) setPill(pill, 'recording', 'ok', 'live');
  else if (state.lastSessionId) setPill(pill, 'stopped', 'unknown', 'stopped');
  else setPill(pill, 'no session', 'unknown', 'none');
  $('s-performer').textContent = session ? session.performer : (state.lastPerformer || '–');
  if (session) $('s-time').textContent = fmtDuration(session.time_s);
  $('session-info').textContent = session
    ? `session ${session.id} · ${fmtInt(session.frames)} frames${session.fit_error ? ' · ' + session.fit_error : ''}`
    : (state.lastSessionId ? `last session ${state.lastSessionId} (stopped)` : 'no live session');
  $('dl-skeleton').disabled = !state.lastSessionId;
  $('dl-take').disabled = !state.lastSessionId;
  $('dl-bvh').disabled = !state.lastSessionId;
  $('dl-gltf').disabled = !state.lastSessionId;
  $('dl-trc').disabled = !state.lastSessionId;
}

// A page opened (or a session found) mid-session: the websocket replays only its last few seconds of
// residuals, so the plot's window and the slips in it come from the REST API (a slip 2 min in keeps its
// marker on a page loaded at 2:30). Samples the websocket has delivered meanwhile are kept as they are.
async function backfill(session) {
  const since = Math.max(0, (Number(session.time_s) || 0) - WINDOW_S);
  const base = `/api/sessions/${encodeURIComponent(session.id)}`;
  try {
    const series = await api(`${base}/residuals?since=${since}`);
    if (!state.session || state.session.id !== session.id) return;
    residuals.prepend(series);
    let after = 0;
    for (let page = 0; page < 20; page += 1) {  // 20 pages of 1000 events: more than any session holds
      const got = await api(`${base}/events?since=${after}&limit=1000`);
      if (!state.session || state.session.id !== session.id) return;
      for (const e of got.events) if (e.type === 'slip' || e.type === 'swap') residuals.addSlip(slipMarker(e));
      if (!got.more) break;
      after = got.next_since;
    }
  } catch (e) { /* the live plot still fills from the websocket */ }
}

function resetSessionViews() {
  state.fit = null;
  state.progress = null;
  state.conflicts.clear();
  residuals.clear();
  $('alerts').innerHTML = '<div class="muted small none">No alerts.</div>';
}

async function loadPresets() {
  try {
    const presets = await api('/api/sessions/presets');
    const sel = $('hierarchy');
    for (const name of Object.keys(presets)) {
      if (name === 'auto') continue;
      const o = document.createElement('option');
      o.value = name;
      o.textContent = `known skeleton: ${name}`;
      sel.appendChild(o);
    }
  } catch (e) { /* presets are optional */ }
}

$('session-form').addEventListener('submit', async (e) => {
  e.preventDefault();
  const body = { performer: $('performer').value.trim() };
  if ($('hierarchy').value !== 'auto') body.skeleton = $('hierarchy').value;
  $('start').disabled = true;
  try {
    const s = await api('/api/sessions', { method: 'POST', json: body });
    setSession({ id: s.id, performer: s.performer, frames: 0, time_s: 0 });
  } catch (err) {
    $('start').disabled = false;
    addAlert('error', `Could not start the session: ${err.message}`);
  }
});

$('stop').addEventListener('click', async () => {
  if (!state.session) return;
  const id = state.session.id;
  $('stop').disabled = true;
  try {
    await api(`/api/sessions/${encodeURIComponent(id)}/stop`, { method: 'POST' });
    setSession(null);
  } catch (err) {
    $('stop').disabled = false;
    addAlert('error', `Could not stop the session: ${err.message}`);
  }
});

async function downloadFile(kind) {
  const id = state.lastSessionId;
  if (!id) return;
  const who = (state.lastPerformer || 'session').replace(/[^A-Za-z0-9_.-]+/g, '_');
  try {
    const base = `/api/sessions/${encodeURIComponent(id)}`;
    if (kind === 'skeleton') await download(`${base}/skeleton`, `${who}-${id}-skeleton.json`);
    else if (kind === 'bvh') await download(`${base}/bvh`, `${who}-${id}.bvh`);
    else if (kind === 'glTF') await download(`${base}/gltf`, `${who}-${id}.glb`);
    else if (kind === 'TRC') await download(`${base}/trc`, `${who}-${id}.trc`);
    else await download(`${base}/take`, `${who}-${id}.npz`);
  } catch (err) {
    const why = err instanceof ApiError && err.status === 409 ? 'no fit yet — move a little first' : err.message;
    addAlert('error', `Could not download the ${kind}: ${why}`);
  }
}
$('dl-skeleton').addEventListener('click', () => downloadFile('skeleton'));
$('dl-take').addEventListener('click', () => downloadFile('take'));
$('dl-bvh').addEventListener('click', () => downloadFile('bvh'));
$('dl-gltf').addEventListener('click', () => downloadFile('glTF'));
$('dl-trc').addEventListener('click', () => downloadFile('TRC'));

// ---------------------------------------------------------------------------------- the fit

// The service's standing of the joint named by `child` (every sensor but the root has one).
function standingOf(child) {
  return ((state.progress && state.progress.joint_progress) || []).find((x) => x.joint === child) || null;
}

// Joint spheres: green when calibrated, amber while pinned but not counted yet, grey while not determined.
function jointColour(j) {
  if (!j) return 'none';
  if (j.done) return 'done';
  return ['pinning', 'confirming', 'unsettled'].includes(j.state) ? 'work' : 'none';
}

function showFit(msg) {
  const result = msg.result;
  if (!result) return;
  // A fit of the session just stopped, sent before its stop: its hints are over (showStopped).
  if (!state.session && msg.session && msg.session.id === state.stoppedId) return;
  state.fit = result;
  state.progress = msg;
  view.setFit(result);
  const jointState = {};
  for (const name of result.sensors || []) jointState[name] = 'none';
  for (const j of msg.joint_progress || []) jointState[j.joint] = jointColour(j);
  view.setJointState(jointState);
  showTopology(result);
  showBones(result);
  showCoverage(msg);
  showConflicts(result);
  $('s-joints').textContent = `${msg.joints_done ?? 0} / ${msg.joints_needed ?? Math.max(0, (result.sensors || []).length - 1)}`;
  $('s-joints').dataset.done = msg.done ? 'true' : 'false';
  $('s-joints').dataset.fitSeq = String(msg.fit_seq);
  $('s-fit').textContent = `${fmtInt(result.frames)} frames`;
}

function showTopology(result) {
  const el = $('topology');
  el.classList.remove('muted');
  el.innerHTML = '';
  if (!result.root) { el.textContent = 'No fit yet.'; return; }
  const children = {};
  for (const [child, parent] of Object.entries(result.parent || {})) (children[parent] = children[parent] || []).push(child);
  const joint = {};
  for (const j of result.joints || []) joint[j.child] = j;
  const human = result.humanoid || null;
  const conflicted = {};
  for (const c of result.humanoid_conflicts || []) conflicted[c.sensor] = c;
  const build = (name) => {
    const li = document.createElement('li');
    const label = document.createElement('span');
    label.className = 'node';
    label.textContent = readable(name);
    li.appendChild(label);
    if (human && human[name]) {
      // The body the data found this sensor on, whatever it is called (a name that says otherwise: warned).
      const found = document.createElement('span');
      found.className = `found${conflicted[name] ? ' conflict' : ''}`;
      found.dataset.bone = human[name];
      found.dataset.sensor = name;
      found.textContent = `on the ${foundOn(result, name)}`;
      if (conflicted[name]) found.title = conflicted[name].message;
      li.appendChild(found);
    }
    const j = joint[name];
    const st = standingOf(name);
    if (name === result.root) li.appendChild(badge('root', 'root'));
    else if (!j || (st && st.state === 'rigid')) li.appendChild(badge('rigid', 'moves rigidly with its parent so far — not fitted yet'));
    else if (st && !st.done && (st.state === 'undetermined' || st.state === 'not_turned')) {
      li.appendChild(badge('undetermined', `${jointName(result, name, j.parent)}: ${st.why}`));
    } else {
      if (j.hinge) li.appendChild(badge('hinge', 'turns about one axis only'));
      const b = badge(st && st.done ? 'ok' : 'todo', jointName(result, name, j.parent));
      if (st && st.why) b.title = st.why;
      li.appendChild(b);
    }
    const kids = (children[name] || []).sort();
    if (kids.length) { const ul = document.createElement('ul'); kids.forEach((k) => ul.appendChild(build(k))); li.appendChild(ul); }
    return li;
  };
  const ul = document.createElement('ul');
  ul.appendChild(build(result.root));
  el.appendChild(ul);
  const loops = result.loop_candidates || [];
  const notes = [];
  if (loops.length) notes.push(`closed loop? ${loops.map((l) => `${readable(l.a)}–${readable(l.b)}`).join(', ')}`);
  if (result.ambiguous && result.ambiguous.length) notes.push(`${result.ambiguous.length} ambiguous parent(s)`);
  const note = $('topology-note');
  note.dataset.humanoid = human ? 'found' : 'none';
  if (human) notes.push('limbs found from the motion');
  else if (result.humanoid_note) notes.push('not a human tree: sensor names kept');
  note.textContent = notes.join(' · ');
  note.title = human ? '' : (result.humanoid_note || '');
}

// Sensors whose names say another limb than the one the data found them on: one alert each (the outputs
// follow the data; the operator checks the strap or the name).
function showConflicts(result) {
  for (const c of result.humanoid_conflicts || []) {
    const id = `conflict-${c.sensor}-${c.found}`;
    if (state.conflicts.has(id)) continue;
    state.conflicts.add(id);
    addAlert('warn conflict', `Name and limb disagree: ${c.message}`, id);
  }
}

function badge(kind, text) {
  const s = document.createElement('span');
  // An undetermined joint looks like one not fitted: no bone is drawn for either.
  s.className = `badge badge-${kind === 'undetermined' ? 'rigid' : kind}`;
  s.dataset.kind = kind;
  s.textContent = text;
  if (kind === 'rigid') { s.textContent = 'not fitted'; s.title = text; }
  if (kind === 'undetermined') { s.textContent = 'not determined'; s.title = text; }
  if (kind === 'hinge') { s.textContent = 'hinge'; s.title = text; }
  return s;
}

function showBones(result) {
  const tbody = $('bones').querySelector('tbody');
  tbody.innerHTML = '';
  const parent = result.parent || {};
  for (const b of result.bones || []) {
    if (!Number.isFinite(b.length_m)) continue;
    const tr = document.createElement('tr');
    tr.dataset.body = b.body;
    tr.dataset.from = b.from_joint || '';
    tr.dataset.to = b.to_joint;
    tr.dataset.lengthM = b.length_m;
    tr.dataset.stderrM = b.stderr_m;
    const from = b.from_joint ? jointName(result, b.from_joint, parent[b.from_joint]) : '—';
    const cells = [foundOn(result, b.body), `${from} → ${jointName(result, b.to_joint, parent[b.to_joint])}`,
      `${(b.length_m * 100).toFixed(1)} cm`, Number.isFinite(b.stderr_m) ? `${(b.stderr_m * 1000).toFixed(1)} mm` : '–'];
    cells.forEach((text, k) => {
      const td = document.createElement('td');
      td.textContent = text;
      if (k >= 2) td.className = 'num';
      tr.appendChild(td);
    });
    tbody.appendChild(tr);
  }
  if (!tbody.children.length) tbody.innerHTML = '<tr class="placeholder"><td colspan="4" class="muted">No joints fitted yet: move the performer.</td></tr>';
}

// The session stopped (here, from the kiosk, a lease or a limit): its "move next" hints no longer apply. Say
// where it ended instead; the bars stay as it left them.
function showStopped(session) {
  state.stoppedId = session.id;
  const todo = $('next-moves');
  if (!todo) return;
  const p = state.progress && state.progress.session && state.progress.session.id === session.id ? state.progress : null;
  todo.className = 'next-moves stopped';
  todo.dataset.state = 'stopped';
  const reached = p ? (p.done ? ': every joint was calibrated' : `: ${p.joints_done ?? 0} of ${p.joints_needed ?? '?'} joints calibrated`) : '';
  todo.textContent = `Session ${session.id} stopped${reached}. Start a session to calibrate again.`;
}

// One bar per sensor but the root, as the service counts it, furthest from calibrated first, under the
// service's own "move next" sentences.
function showCoverage(msg) {
  const el = $('coverage');
  el.innerHTML = '';
  const hints = msg.hints || [];
  const hintFor = {};
  for (const h of hints) hintFor[h.joint] = h.hint;
  const joints = (msg.joint_progress || []).slice().sort((a, b) => (a.done - b.done) || (a.progress - b.progress));
  const todo = document.createElement('div');
  todo.id = 'next-moves';
  todo.className = 'next-moves';
  if (msg.done) {
    todo.classList.add('all-done');
    todo.textContent = `Every joint is calibrated (pinned to ${(1000 * msg.target_m).toFixed(1)} mm).`;
  } else if (hints.length) {
    const title = document.createElement('div');
    title.className = 'next-title';
    title.textContent = 'Move next';
    todo.appendChild(title);
    for (const h of hints.slice(0, 3)) { const d = document.createElement('div'); d.className = 'hint'; d.textContent = h.hint; todo.appendChild(d); }
  }
  el.appendChild(todo);
  for (const j of joints) {
    const p = Math.max(0, Math.min(1, Number(j.progress) || 0));
    const row = document.createElement('div');
    row.className = 'cov';
    row.dataset.joint = j.joint;
    row.dataset.progress = p;
    row.dataset.state = j.state;
    row.dataset.done = j.done ? 'true' : 'false';
    const name = document.createElement('span');
    name.className = 'cov-name';
    name.textContent = j.label;
    name.title = `${readable(j.parent)} → ${readable(j.joint)}${j.why ? ': ' + j.why : ''}${hintFor[j.joint] ? ' — ' + hintFor[j.joint] : ''}`;
    const bar = document.createElement('div');
    bar.className = `bar ${j.done ? 'full' : p < 0.5 ? 'low' : ''}`;
    const fill = document.createElement('div');
    fill.style.width = `${Math.max(2, p * 100).toFixed(0)}%`;
    bar.appendChild(fill);
    const value = document.createElement('span');
    value.className = 'cov-value';
    value.textContent = j.done ? '✓' : `${Math.floor(p * 100 + 1e-9)}%`;
    const sd = document.createElement('span');
    sd.className = 'cov-sd';
    sd.textContent = Number.isFinite(j.error_m) ? `±${(j.error_m * 1000).toFixed(1)} mm` : '';
    sd.title = 'how closely the data pin the joint centre along the worst direction it needs';
    row.append(name, bar, value, sd);
    el.appendChild(row);
  }
}

// ---------------------------------------------------------------------------------- residual plot

const palette = ['#58a6ff', '#ffc857', '#7ee787', '#ff7b72', '#d2a8ff', '#79c0ff', '#ffa657', '#56d4dd',
  '#f778ba', '#a5d6ff', '#e3b341', '#8ddb8c', '#ffb3ad', '#bc8cff', '#39c5cf', '#f0883e'];

// Residual samples on one time axis, one column per joint ever seen this session; slips as markers.
const residuals = {
  times: [], cols: {}, names: [], slips: [], plot: null, built: '', ymax: 5,
  clear() {
    this.times = []; this.cols = {}; this.names = []; this.slips = [];
    this.draw();
  },
  add(msg) {
    const times = msg.times || [];
    const joints = msg.joints || {};
    for (const name of Object.keys(joints)) {
      if (!this.cols[name]) { this.cols[name] = this.times.map(() => null); this.names.push(name); this.names.sort(); }
    }
    let last = this.times.length ? this.times[this.times.length - 1] : -Infinity;
    times.forEach((t, k) => {
      if (!(t > last)) return;  // a replayed or duplicate sample
      last = t;
      this.times.push(t);
      for (const name of this.names) this.cols[name].push(joints[name] ? joints[name][k] ?? null : null);
    });
    this.trim();
    this.draw();
  },
  // Keep the last WINDOW_S seconds.
  trim() {
    const last = this.times.length ? this.times[this.times.length - 1] : 0;
    const cut = this.times.findIndex((t) => t >= last - WINDOW_S);
    if (cut > 0) {
      this.times.splice(0, cut);
      for (const name of this.names) this.cols[name].splice(0, cut);
    }
  },
  // Older samples (the REST series) before the ones the websocket brought.
  prepend(msg) {
    const first = this.times.length ? this.times[0] : Infinity;
    const times = (msg && msg.times) || [];
    const joints = (msg && msg.joints) || {};
    const keep = [];
    times.forEach((t, k) => { if (t < first && (!keep.length || t > times[keep[keep.length - 1]])) keep.push(k); });
    if (!keep.length) return;
    for (const name of Object.keys(joints)) {
      if (!this.cols[name]) { this.cols[name] = this.times.map(() => null); this.names.push(name); }
    }
    this.names.sort();
    this.times = keep.map((k) => times[k]).concat(this.times);
    for (const name of this.names) {
      const src = joints[name];
      this.cols[name] = keep.map((k) => (src ? src[k] ?? null : null)).concat(this.cols[name]);
    }
    this.trim();
    this.draw();
  },
  addSlip(ev) {
    if (this.slips.some((s) => s.id === ev.id)) return;
    this.slips.push(ev);
    $('residuals').dataset.slips = this.slips.length;
    this.draw();
  },
  draw() {
    const el = $('residuals');
    el.dataset.samples = this.times.length;
    el.dataset.first = this.times.length ? this.times[0] : '';
    el.dataset.slips = this.slips.length;
    // Labels depend on the newest topology ("mid back" vs "lower back"): rebuild when they change.
    const key = this.labels().join(',');
    if (!this.plot || key !== this.built) this.build();
    // Scale to the bulk of the data: the first second of a young fit can read hundreds of mm and
    // would flatten everything after it (those spikes run off the top instead).
    const values = [];
    for (const n of this.names) for (const v of this.cols[n]) if (Number.isFinite(v)) values.push(v);
    values.sort((x, y) => x - y);
    this.ymax = values.length ? Math.max(5, 1.25 * values[Math.floor(0.995 * (values.length - 1))]) : 5;
    const data = [this.times].concat(this.names.map((n) => this.cols[n]));
    this.plot.setData(data);
  },
  labels() {
    return this.names.map((j) => jointName(state.fit, j));
  },
  build() {
    const el = $('residuals');
    el.innerHTML = '';
    const labels = this.labels();
    this.built = labels.join(',');
    const self = this;
    const opts = {
      width: el.clientWidth || 900,
      height: PLOT_HEIGHT,
      scales: { x: { time: false }, y: { range: () => [0, self.ymax || 5] } },
      axes: [
        { stroke: '#8b98a5', grid: { stroke: '#21262d' }, ticks: { stroke: '#30363d' }, label: 'session time (s)', labelSize: 18 },
        { stroke: '#8b98a5', grid: { stroke: '#21262d' }, ticks: { stroke: '#30363d' }, label: 'residual (mm)', labelSize: 18, size: 50 },
      ],
      series: [{ label: 't' }].concat(this.names.map((j, i) => ({
        label: labels[i], stroke: palette[i % palette.length], width: 1.4, spanGaps: false,
        value: (u, v) => (v === null || v === undefined ? '–' : `${v.toFixed(1)} mm`),
      }))),
      cursor: { drag: { x: false, y: false } },
      legend: { live: false },
      plugins: [{ hooks: { draw: [(u) => drawSlips(u, self.slips)] } }],
    };
    this.plot = new uPlot(opts, [[]].concat(this.names.map(() => [])), el);
  },
};

function drawSlips(u, slips) {
  const ctx = u.ctx;
  const dpr = window.devicePixelRatio || 1;
  ctx.save();
  ctx.strokeStyle = '#f85149';
  ctx.fillStyle = '#f85149';
  ctx.lineWidth = 2 * dpr;
  ctx.setLineDash([6 * dpr, 4 * dpr]);
  ctx.font = `${11 * dpr}px system-ui, sans-serif`;
  slips.forEach((s, k) => {
    const x = u.valToPos(s.time_s, 'x', true);
    if (!(x >= u.bbox.left && x <= u.bbox.left + u.bbox.width)) return;
    ctx.beginPath(); ctx.moveTo(x, u.bbox.top); ctx.lineTo(x, u.bbox.top + u.bbox.height); ctx.stroke();
    // Stagger the labels so slips close together stay readable.
    ctx.fillText(` slip: ${readable(s.sensor)}`, x + 2 * dpr, u.bbox.top + (12 + 13 * (k % 4)) * dpr);
  });
  ctx.restore();
}

new ResizeObserver(() => {
  if (residuals.plot) residuals.plot.setSize({ width: $('residuals').clientWidth, height: PLOT_HEIGHT });
}).observe($('residuals'));

// ---------------------------------------------------------------------------------- alerts

function addAlert(kind, text, id) {
  const alerts = $('alerts');
  if (id !== undefined && alerts.querySelector(`[data-id="${id}"]`)) return;
  alerts.querySelectorAll('.none').forEach((n) => n.remove());
  const div = document.createElement('div');
  div.className = `alert ${kind}`;
  if (id !== undefined) div.dataset.id = id;
  const text_ = document.createElement('span');
  text_.textContent = text;
  const close = document.createElement('button');
  close.type = 'button';
  close.className = 'close';
  close.setAttribute('aria-label', 'dismiss');
  close.textContent = '×';
  close.addEventListener('click', () => div.remove());
  div.append(text_, close);
  alerts.prepend(div);
  while (alerts.children.length > 6) alerts.lastChild.remove();
}

// A sensor as an alert names it: its name, and the limb the data found it on where that says more.
function sensorSaid(sensor) {
  const found = foundOn(state.fit, sensor);
  return found !== readable(sensor) ? `${readable(sensor)} (on the ${found})` : readable(sensor);
}

// A slip or swap event as the residual plot marks it (a swap names both sensors).
function slipMarker(e) {
  if (e.type !== 'swap') return e;
  const [a, b] = e.sensors || e.candidates || [e.a, e.b];
  return Object.assign({ sensor: `${a}⇄${b}` }, e);
}

function showEvent(msg) {
  const e = msg.event || msg;
  const kind = e.type;
  if (kind === 'slip') {
    const who = e.candidates && e.candidates.length > 1 ? e.candidates.map(sensorSaid).join(' or ') : sensorSaid(e.sensor);
    const joints = (e.joints || []).map((j) => jointName(state.fit, j)).join(', ');
    addAlert('slip', `Sensor slipped: ${who} at ${Number(e.time_s).toFixed(1)} s, residual jump ${Number(e.jump_mm).toFixed(0)} mm` +
      `${joints ? ` (${joints})` : ''} — check its strap; those joints re-fit from here.`, e.id);
    if (!state.session || e.session_id === state.session.id) residuals.addSlip(e);
  } else if (kind === 'swap') {
    const [a, b] = e.sensors || e.candidates || [e.a, e.b];
    addAlert('slip', `Sensors swapped: ${readable(a)} ⇄ ${readable(b)} at ${Number(e.time_s).toFixed(1)} s — check the cables.`, e.id);
    if (!state.session || e.session_id === state.session.id) residuals.addSlip(slipMarker(e));
  } else if (kind === 'tracker') {
    if (['disconnected', 'connected', 'reconnecting', 'error', 'stalled', 'bird_error'].includes(e.kind)) {
      addAlert(e.kind === 'connected' ? 'info' : 'warn', `Tracker ${e.kind.replace('_', ' ')}${e.message ? ': ' + e.message : ''}`, e.id);
    }
  } else if (kind === 'session') {
    addAlert('info', e.message || `session ${e.action}`, e.id);
  } else if (kind === 'service') {  // the disk: full (recording stopped) or room again
    addAlert(e.action === 'disk_ok' ? 'info' : 'warn', e.message || `service ${e.action}`, e.id);
  }
}

// ---------------------------------------------------------------------------------- wiring

connectLive({
  content: ['status', 'fit', 'residuals', 'events', 'pose'],
  rateHz: 15,
  onState: showLink,
  onMessage: (msg) => {
    switch (msg.type) {
      case 'status': showStatus(msg.status, msg.time); break;
      case 'fit': showFit(msg); break;
      case 'pose': if (msg.pose) { view.update(msg.pose); $('view-empty').classList.add('hidden'); } break;
      case 'residuals': residuals.add(msg); break;
      case 'event': showEvent(msg); break;
      case 'error': addAlert('error', msg.message); break;
      default: break;
    }
  },
});

residuals.draw();
loadPresets();
api('/api/status').then(showStatus).catch(() => {});
