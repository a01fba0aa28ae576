// The operator dashboard: live skeleton, topology, bones, coverage hints, residual plot with slip
// markers, tracker status and session controls. It only reads what the service publishes.

import { api, connectLive, readable, SkeletonView } from './common.js';

const $ = (id) => document.getElementById(id);
const view = new SkeletonView($('view'));
const WINDOW_S = 30;

let liveSession = null;
const slipTimes = [];           // slip event times (s, session clock) drawn on the residual plot
const residualSeries = {};      // joint -> [[t, mm], ...]
let plot = null;
let plotJoints = [];

function setPill(el, text, kind) {
  el.textContent = text;
  el.className = `pill pill-${kind}`;
}

function showStatus(s) {
  const connected = !!s.connected;
  setPill($('tracker'), connected ? 'tracker connected' : 'tracker disconnected', connected ? 'ok' : 'bad');
  $('tracker').dataset.state = connected ? 'connected' : 'disconnected';
  const rate = s.rate_hz ? `${Number(s.rate_hz).toFixed(0)} Hz` : '– Hz';
  const parts = [`${s.birds ?? '–'} birds`, rate, `${s.frames ?? 0} frames`,
    `${s.dropped_records ?? 0} dropped`, `${s.resynced ?? 0} resyncs`];
  $('tracker-detail').textContent = parts.join(' · ');
  const banner = $('banner');
  if (!connected) {
    banner.textContent = `Tracker disconnected${s.last_error ? ': ' + s.last_error : ''} — reconnecting; the session keeps what it has.`;
    banner.classList.remove('hidden');
  } else {
    banner.classList.add('hidden');
  }
  const session = s.session || s.live_session || null;
  if (session && session.id !== undefined) setLiveSession(session);
  else if (s.session === null || s.live_session === null) setLiveSession(null);
}

function setLiveSession(session) {
  liveSession = session;
  $('start').disabled = !!session;
  $('stop').disabled = !session;
  $('session-info').textContent = session
    ? `live: ${session.performer || session.name || ''} (session ${session.id})`
    : 'no live session';
  const dl = $('downloads');
  dl.innerHTML = '';
  const id = session ? session.id : lastStoppedId;
  if (id !== null && id !== undefined) {
    for (const [label, path] of [['skeleton.json', 'skeleton'], ['take.bvh', 'bvh'], ['result.json', 'result']]) {
      const a = document.createElement('a');
      a.href = `/api/sessions/${encodeURIComponent(id)}/${path}`;
      a.textContent = `download ${label}`;
      a.setAttribute('download', `${session ? session.performer || 'session' : 'session'}-${id}-${label}`);
      dl.appendChild(a);
    }
  }
}
let lastStoppedId = null;

function showTopology(result) {
  const children = {};
  for (const [child, parent] of Object.entries(result.parent || {})) (children[parent] = children[parent] || []).push(child);
  const hinge = {};
  for (const j of result.joints || []) hinge[j.child] = j.hinge;
  const build = (name) => {
    const li = document.createElement('li');
    li.textContent = readable(name);
    if (hinge[name]) { const s = document.createElement('span'); s.className = 'hinge'; s.textContent = ' hinge'; li.appendChild(s); }
    const kids = (children[name] || []).sort();
    if (kids.length) { const ul = document.createElement('ul'); kids.forEach((k) => ul.appendChild(build(k))); li.appendChild(ul); }
    return li;
  };
  const el = $('topology');
  el.classList.remove('muted');
  el.innerHTML = '';
  if (!result.root) { el.textContent = 'waiting for data…'; return; }
  const ul = document.createElement('ul');
  ul.appendChild(build(result.root));
  el.appendChild(ul);
}

function showBones(result) {
  const tbody = $('bones').querySelector('tbody');
  tbody.innerHTML = '';
  for (const b of result.bones || []) {
    const tr = document.createElement('tr');
    tr.dataset.body = b.body;
    tr.dataset.lengthM = b.length_m;
    const from = b.from_joint ? readable(b.from_joint) : '—';
    tr.innerHTML = `<td></td><td></td><td class="num"></td><td class="num"></td>`;
    tr.children[0].textContent = readable(b.body);
    tr.children[1].textContent = `${from} → ${readable(b.to_joint)}`;
    tr.children[2].textContent = `${(b.length_m * 100).toFixed(1)} cm`;
    tr.children[3].textContent = Number.isFinite(b.stderr_m) ? `${(b.stderr_m * 1000).toFixed(1)} mm` : '–';
    tbody.appendChild(tr);
  }
}

function showCoverage(result, hints) {
  const el = $('coverage');
  el.innerHTML = '';
  const hintFor = {};
  for (const h of hints || []) hintFor[h.joint || h.child] = h.hint || h.text;
  for (const j of result.joints || []) {
    const cov = j.coverage || [0, 0, 0];
    // A ball joint needs all three axes exercised, a hinge only its own: judge by the weakest needed axis.
    const needed = j.hinge ? [Math.max(...cov)] : cov;
    const level = Math.max(0, Math.min(1, Math.min(...needed) / 0.15));
    const row = document.createElement('div');
    row.className = 'cov';
    row.innerHTML = `<span></span><div class="bar"><div></div></div>`;
    row.children[0].textContent = readable(j.child);
    row.children[1].children[0].style.width = `${(level * 100).toFixed(0)}%`;
    if (level < 0.5) row.children[1].classList.add('low');
    el.appendChild(row);
    const hint = hintFor[j.child];
    if (hint) { const h = document.createElement('div'); h.className = 'hint'; h.textContent = hint; row.appendChild(h); }
  }
}

function slipMarkersPlugin() {
  return {
    hooks: {
      draw: (u) => {
        const ctx = u.ctx;
        ctx.save();
        ctx.strokeStyle = '#f85149';
        ctx.lineWidth = 2 * (window.devicePixelRatio || 1);
        for (const t of slipTimes) {
          const x = u.valToPos(t, 'x', true);
          if (x < u.bbox.left || x > u.bbox.left + u.bbox.width) continue;
          ctx.beginPath(); ctx.moveTo(x, u.bbox.top); ctx.lineTo(x, u.bbox.top + u.bbox.height); ctx.stroke();
        }
        ctx.restore();
      },
    },
  };
}

const palette = ['#3fa9f5', '#ffc857', '#7ee787', '#ff7b72', '#d2a8ff', '#79c0ff', '#ffa657', '#56d4dd',
  '#f778ba', '#a5d6ff', '#e3b341', '#8ddb8c', '#ffb3ad', '#bc8cff', '#39c5cf', '#f0883e'];

function rebuildPlot(joints) {
  plotJoints = joints;
  const el = $('residuals');
  el.innerHTML = '';
  const opts = {
    width: el.clientWidth || 800, height: 240,
    scales: { x: { time: false } },
    axes: [{ stroke: '#8b98a5', label: 's' }, { stroke: '#8b98a5', label: 'mm' }],
    series: [{}].concat(joints.map((j, i) => ({ label: readable(j), stroke: palette[i % palette.length], width: 1.2 }))),
    plugins: [slipMarkersPlugin()],
    legend: { live: false },
  };
  plot = new uPlot(opts, [[]].concat(joints.map(() => [])), el);
  el.dataset.series = joints.length;
}

function addResiduals(msg) {
  // {times: [...], joints: {child: [mm, ...]}} — samples since the last message.
  const times = msg.times || msg.t || [];
  const joints = msg.joints || {};
  const names = Object.keys(joints).sort();
  if (!plot || names.join() !== plotJoints.join()) rebuildPlot(names);
  for (const name of names) {
    const s = residualSeries[name] = residualSeries[name] || [];
    joints[name].forEach((v, k) => s.push([times[k], v]));
  }
  const tEnd = times.length ? times[times.length - 1] : 0;
  for (const name of names) {
    const s = residualSeries[name];
    while (s.length && s[0][0] < tEnd - WINDOW_S) s.shift();
  }
  const xs = (residualSeries[names[0]] || []).map((p) => p[0]);
  const data = [xs].concat(names.map((n) => {
    const byT = new Map(residualSeries[n].map((p) => [p[0], p[1]]));
    return xs.map((t) => (byT.has(t) ? byT.get(t) : null));
  }));
  plot.setData(data);
  $('residuals').dataset.samples = xs.length;
}

function showEvent(ev) {
  const e = ev.event || ev;
  const kind = e.type || e.kind;
  const div = document.createElement('div');
  if (kind === 'slip') {
    slipTimes.push(e.time_s);
    div.className = 'alert slip';
    const who = e.candidates && e.candidates.length > 1 ? e.candidates.map(readable).join(' or ') : readable(e.sensor);
    div.textContent = `Sensor slipped: ${who} at ${Number(e.time_s).toFixed(1)} s (jump ${Number(e.jump_mm).toFixed(0)} mm) — check the strap; those joints are re-fitting.`;
    if (plot) plot.redraw();
  } else if (kind === 'swap') {
    div.className = 'alert swap';
    div.textContent = `Sensors swapped: ${readable(e.a || (e.sensors || [])[0])} ⇄ ${readable(e.b || (e.sensors || [])[1])} at ${Number(e.time_s).toFixed(1)} s — check the cables.`;
  } else {
    div.className = 'alert info';
    div.textContent = e.message || `${kind}`;
  }
  const alerts = $('alerts');
  alerts.prepend(div);
  while (alerts.children.length > 8) alerts.lastChild.remove();
}

connectLive({
  content: ['status', 'fit', 'residuals', 'events', 'pose'],
  rateHz: 15,
  onState: (state) => setPill($('link'), state === 'open' ? 'server: live' : 'server: reconnecting…', state === 'open' ? 'ok' : 'warn'),
  onMessage: (msg) => {
    switch (msg.type) {
      case 'status': showStatus(msg.status || msg); break;
      case 'fit': {
        const result = msg.result || msg.fit || msg;
        showTopology(result); showBones(result); showCoverage(result, msg.hints || result.hints);
        break;
      }
      case 'pose': view.update(msg); break;
      case 'residuals': addResiduals(msg); break;
      case 'event': showEvent(msg); break;
      case 'error': showEvent({ type: 'info', message: msg.message }); break;
      default: break;
    }
  },
});

$('session-form').addEventListener('submit', async (e) => {
  e.preventDefault();
  const body = { performer: $('performer').value.trim() };
  if ($('hierarchy').value !== 'auto') body.skeleton = $('hierarchy').value;
  try {
    const s = await api('/api/sessions', { method: 'POST', json: body });
    setLiveSession(s);
    Object.keys(residualSeries).forEach((k) => delete residualSeries[k]);
    slipTimes.length = 0;
  } catch (err) { showEvent({ type: 'info', message: `Could not start: ${err.message}` }); }
});

$('stop').addEventListener('click', async () => {
  if (!liveSession) return;
  try {
    await api(`/api/sessions/${encodeURIComponent(liveSession.id)}/stop`, { method: 'POST' });
    lastStoppedId = liveSession.id;
    setLiveSession(null);
  } catch (err) { showEvent({ type: 'info', message: `Could not stop: ${err.message}` }); }
});

api('/api/status').then(showStatus).catch(() => {});
window.addEventListener('resize', () => { if (plot) plot.setSize({ width: $('residuals').clientWidth, height: 240 }); });
