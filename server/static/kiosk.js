// The guest-facing kiosk: an avatar that follows the guest, a progress ring fed by coverage and
// uncertainty, what to move next, and a "done" state; one session per guest, then it resets itself.
// URL options: ?token=… (kiosk token), &stderr_mm=5 (joint uncertainty counted as calibrated),
// &reset_s=10 (how long "done" stays up before the next guest).

import { api, connectLive, readable, SkeletonView } from './common.js';

const $ = (id) => document.getElementById(id);
const params = new URLSearchParams(location.search);
const TARGET_STDERR_M = Number(params.get('stderr_mm') || 5) / 1000;
const RESET_S = Number(params.get('reset_s') || 10);
const COVERAGE_FULL = 0.15;   // 1 − σ(M) per axis counted as "moved enough" (design.md §3)

const avatar = new SkeletonView($('avatar'), { autoRotate: false, colour: 0x7ee787 });
const ring = $('ring-fill');
const CIRC = 2 * Math.PI * 84;
ring.style.strokeDasharray = `${CIRC}`;
ring.style.strokeDashoffset = `${CIRC}`;

let session = null;
let state = 'starting';
let trackerOk = true;

function setState(s, text) {
  state = s;
  $('kiosk-state').dataset.state = s;
  $('kiosk-state').textContent = text;
  document.body.classList.toggle('done', s === 'done');
}

function setProgress(p) {
  const clamped = Math.max(0, Math.min(1, p));
  ring.style.strokeDashoffset = `${CIRC * (1 - clamped)}`;
  $('percent').textContent = `${Math.floor(clamped * 100)}%`;
}

// Per joint: how far both coverage (all needed axes exercised) and uncertainty (stderr under the
// target) have come; the guest is done when every joint is there.
export function jointProgress(j) {
  const cov = j.coverage || [0, 0, 0];
  const needed = j.hinge ? [Math.max(...cov)] : cov;
  const c = Math.min(1, Math.min(...needed) / COVERAGE_FULL);
  const err = Math.max(j.c_stderr_m ?? Infinity, j.l_stderr_m ?? Infinity);
  const u = Number.isFinite(err) ? Math.min(1, TARGET_STDERR_M / Math.max(err, 1e-9)) : 0;
  return Math.min(c, u);
}

function instructionFor(joints) {
  let worst = null;
  for (const j of joints) { const p = jointProgress(j); if (!worst || p < worst.p) worst = { j, p }; }
  if (!worst) return 'Wave your arms and march on the spot!';
  const name = readable(worst.j.child);
  if (/foot|shin|thigh|knee|leg/.test(name)) return `Lift your ${name.replace('shin', 'knee')} and wiggle it!`;
  if (/hand|forearm|arm|elbow/.test(name)) return `Swing your ${name} in big circles!`;
  if (/head|neck/.test(name)) return 'Nod and shake your head slowly!';
  return `Twist and bend your ${name}!`;
}

async function startGuest() {
  setState('starting', 'getting ready…');
  setProgress(0);
  try {
    const stamp = new Date().toTimeString().slice(0, 8);
    session = await api('/api/sessions', { method: 'POST', json: { performer: `guest ${stamp}` } });
    setState('live', 'calibrating');
    $('instruction').textContent = 'Wave your arms and march on the spot!';
  } catch (err) {
    // A session may already be live (an operator's, or ours after a reload): follow it instead.
    try {
      const st = await api('/api/status');
      session = st.session || st.live_session || null;
    } catch (e) { session = null; }
    if (session) setState('live', 'calibrating');
    else { setState('error', `waiting for the service (${err.message})`); setTimeout(startGuest, 3000); }
  }
}

async function finishGuest() {
  setState('done', 'done!');
  $('instruction').textContent = 'All set — enjoy the show!';
  setProgress(1);
  try { if (session) await api(`/api/sessions/${encodeURIComponent(session.id)}/stop`, { method: 'POST' }); } catch (e) { /* already stopped */ }
  session = null;
  setTimeout(startGuest, RESET_S * 1000);
}

function onFit(result) {
  if (state !== 'live') return;
  const joints = result.joints || [];
  if (!joints.length) return;
  const ps = joints.map(jointProgress);
  const overall = ps.reduce((a, b) => a + b, 0) / ps.length;
  setProgress(overall);
  if (ps.every((p) => p >= 1)) finishGuest();
  else $('instruction').textContent = instructionFor(joints);
}

function onStatus(s) {
  trackerOk = !!s.connected;
  const banner = $('banner');
  if (!trackerOk) {
    banner.textContent = 'The tracker is disconnected — please ask a host for help.';
    banner.classList.remove('hidden');
    $('kiosk-state').dataset.tracker = 'disconnected';
  } else {
    banner.classList.add('hidden');
    $('kiosk-state').dataset.tracker = 'connected';
  }
}

connectLive({
  content: ['status', 'fit', 'pose'],
  rateHz: 10,
  onState: (st) => {
    if (st !== 'open') { $('banner').textContent = 'Reconnecting to the calibration service…'; $('banner').classList.remove('hidden'); }
    else if (trackerOk) $('banner').classList.add('hidden');
  },
  onMessage: (msg) => {
    if (msg.type === 'status') onStatus(msg.status || msg);
    else if (msg.type === 'fit') onFit(msg.result || msg.fit || msg);
    else if (msg.type === 'pose') avatar.update(msg);
  },
});

startGuest();
