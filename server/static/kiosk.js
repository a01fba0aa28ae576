// The guest-facing kiosk: an avatar that follows the guest, a progress ring, what to move next, and a
// "done" state; one session per guest, then it resets itself. The ring, the chips and "done" are the
// service's progress as published (docs/service.md, Progress): the page computes none of it.
// URL options: ?token=… (a kiosk token starts and stops sessions; a read-only token follows the
// sessions a host starts), reset_s=10 (how long "done" stays up), max_s=300 (a guest who walks away:
// start afresh), mirror=0 (show the avatar as others see the guest, not as a mirror), lease_s=30 (a guest's
// session ends this long after this page stops renewing it: closed, crashed or unplugged), operator=1 (the
// attendant's strip along the bottom: which limb each sensor was found on, and any sensor whose name says
// another limb; guests see neither).

import { api, ApiError, connectLive, foundOn, readable, SkeletonView } from './common.js';

const $ = (id) => document.getElementById(id);
const params = new URLSearchParams(location.search);
const num = (key, fallback) => {
  const v = Number(params.get(key));
  return params.has(key) && Number.isFinite(v) && v > 0 ? v : fallback;
};
const RESET_S = num('reset_s', 10);
const MAX_S = num('max_s', 300);
const LEASE_S = num('lease_s', 30);
const OPERATOR = params.get('operator') === '1';

const avatar = new SkeletonView($('avatar'), { colour: 0x7ee787, follow: true, mirror: params.get('mirror') !== '0' });
const ring = $('ring-fill');
const CIRC = 2 * Math.PI * 86;
ring.style.strokeDasharray = `${CIRC}`;
ring.style.strokeDashoffset = `${CIRC}`;

const kiosk = {
  state: 'starting',       // starting | live | done | waiting | busy | error
  session: null,           // the session being shown {id, performer}
  owned: false,            // started by a kiosk, so the kiosk stops it when the guest is done
  canControl: true,        // false with a read-only token: follow the host's sessions instead
  startedAt: 0,
  timer: null,
  lastStatus: null,
  doneSession: null,       // a host's session shown as done until it ends
  renewer: null,           // the interval renewing an owned session's lease
};

// While this page follows a session it started, it renews the session's lease a few times per lease:
// if the page goes away, the service ends the session after LEASE_S instead of blocking the next guest.
function keepLease(session) {
  if (kiosk.renewer) { clearInterval(kiosk.renewer); kiosk.renewer = null; }
  if (!session) return;
  kiosk.renewer = setInterval(() => {
    if (!kiosk.session || kiosk.session.id !== session.id || !kiosk.owned) { keepLease(null); return; }
    api(`/api/sessions/${encodeURIComponent(session.id)}/lease`, { method: 'POST' }).catch(() => {});
  }, Math.max(1000, (LEASE_S * 1000) / 5));
}

const TITLES = { done: 'Calibrated!', waiting: 'Welcome!', busy: 'One moment…', error: 'One moment…' };

function setState(s, text) {
  kiosk.state = s;
  $('title').textContent = TITLES[s] || "Let's get you calibrated";
  const el = $('kiosk-state');
  el.dataset.state = s;
  el.textContent = text;
  document.body.classList.toggle('done', s === 'done');
  // Busy: someone else's session is on the stage; the avatar (their body) is not shown to the guest.
  document.body.classList.toggle('busy', s === 'busy');
}

// A session this kiosk (or another kiosk page) started for a guest: its profile and its performer's name
// say so. Any other live session is an operator's, which a guest never sees as theirs.
const isGuestSession = (s) => s.profile === 'kiosk' && /^guest /.test(s.performer || '');

// The stage is in use by an operator's session: a clear screen that says so, until it ends (onStatus).
function stageInUse() {
  clearTimer();
  kiosk.session = null;
  keepLease(null);
  setState('busy', 'the stage is in use — your calibration starts as soon as it is free');
  setProgress(0, 0, null);
  $('chips').innerHTML = '';
  $('instruction').textContent = 'The stage is in use right now. Please wait a moment — we start as soon as it is free.';
}

// What to do when the page opens (or the stage frees): start a guest, take back this kiosk's own guest
// after a reload, follow a host's session with a read-only token, or wait while an operator records.
function startOrWait() {
  const live = kiosk.lastStatus && kiosk.lastStatus.session;
  if (!live) { startGuest(); return; }
  if (!kiosk.canControl) { follow(live, false); return; }
  if (isGuestSession(live)) { follow(live, true); return; }
  stageInUse();
}

// The service's figure as it sends it: `percent` is its whole percent (100 only when done).
function setProgress(progress, percent, fitSeq) {
  const p = Math.max(0, Math.min(1, progress));
  ring.style.strokeDashoffset = `${CIRC * (1 - p)}`;
  const el = $('percent');
  el.textContent = `${percent}%`;
  el.dataset.value = String(progress);
  el.dataset.fitSeq = fitSeq === undefined || fitSeq === null ? '' : String(fitSeq);
}

// What a guest should do to move a body's joint, in words a guest uses.
function actionFor(body) {
  const name = readable(body);
  const side = /^(left|right) /.exec(name);
  const s = side ? `${side[1]} ` : '';
  const part = side ? name.slice(side[0].length) : name;
  if (/head|neck/.test(part)) return 'Nod and turn your head slowly!';
  if (/hand|wrist/.test(part)) return `Wave your ${s}hand and roll your wrist!`;
  if (/fore ?arm|lower ?arm|elbow/.test(part)) return `Bend and stretch your ${s}elbow!`;
  if (/arm|shoulder|clavicle/.test(part)) return `Swing your ${s}arm in big circles!`;
  if (/foot|ankle|toe/.test(part)) return `Point your ${s}toes and circle your ${s}foot!`;
  if (/shin|calf|knee|lower ?leg/.test(part)) return `Bend your ${s}knee — kick your heel back!`;
  if (/thigh|leg|hip/.test(part)) return `March! Lift your ${s}knee up high!`;
  if (/pelvis|hips?/.test(part)) return 'Wiggle your hips side to side!';
  if (/chest|abdomen|spine|torso|back|waist/.test(part)) return 'Twist and bend at your waist!';
  return `Move your ${name}!`;
}

// The body part a sensor is on, in a guest's words: the limb the data found it on (whatever the sensor is
// called), else its name read as words.
let shownFit = null;
const part = (sensor) => foundOn(shownFit, sensor);

// One chip per sensor but the root, ticked when the service counts its joint as calibrated.
function showChips(joints, next) {
  const el = $('chips');
  el.innerHTML = '';
  for (const j of joints) {
    const chip = document.createElement('span');
    chip.className = `chip${j.done ? ' done' : ''}${j.joint === next ? ' next' : ''}`;
    chip.dataset.body = j.joint;
    chip.dataset.state = j.state;
    chip.textContent = `${j.done ? '✓ ' : ''}${part(j.joint)}`;
    el.appendChild(chip);
  }
}

// The next thing to do, for the joint the service lists first; if a calibrated joint was undone
// (a sensor slipped), say so, so the guest knows why the ring went back.
function instructionFor(m) {
  const act = actionFor(part(m.joint));
  if (m.undone && m.undone.reason === 'slip') return `Your ${part(m.undone.sensor)} sensor moved — once more: ${act}`;
  if (m.undone && m.undone.reason === 'tree') return `Once more, so your ${part(m.joint)} is placed right: ${act}`;
  if (m.undone) return `Your ${part(m.joint)} needs a little more: ${act}`;
  return act;
}

// The attendant's strip (operator=1): the limb each sensor was found on, and the names that disagree.
function showOperator(result) {
  const el = $('operator');
  if (!OPERATOR || !result) return;
  el.classList.remove('hidden');
  el.innerHTML = '';
  const conflicts = result.humanoid_conflicts || [];
  el.dataset.conflicts = String(conflicts.length);
  for (const c of conflicts) {
    const line = document.createElement('div');
    line.className = 'conflict';
    line.textContent = `⚠ ${c.message}`;
    el.appendChild(line);
  }
  const line = document.createElement('div');
  if (result.humanoid) {
    for (const [sensor, bone] of Object.entries(result.humanoid)) {
      const s = document.createElement('span');
      s.className = 'found';
      s.dataset.sensor = sensor;
      s.dataset.bone = bone;
      s.textContent = `${sensor} → ${foundOn(result, sensor)}`;
      line.appendChild(s);
    }
  } else {
    line.textContent = result.humanoid_note || 'no humanoid yet';
  }
  el.appendChild(line);
}

function onFit(msg) {
  const result = msg.result;
  // A host's session shown as done that a slip has undone: back to calibrating, saying why (below).
  if (kiosk.state === 'done' && kiosk.doneSession && msg.session && msg.session.id === kiosk.doneSession && !msg.done) {
    kiosk.doneSession = null;
    setState('live', `calibrating ${kiosk.session.performer}`);
  }
  if (kiosk.state !== 'live' || !result || !kiosk.session) return;
  if (msg.session && msg.session.id !== kiosk.session.id) return;
  shownFit = result;
  showOperator(result);
  avatar.setFit(result);
  if (msg.rule) $('rule').textContent = msg.rule;
  const joints = msg.joint_progress || [];
  avatar.setJointState(Object.fromEntries(joints.map((j) => [j.joint, jointColour(j)])));
  // A joint undone (a slip, a lost fit) is what the guest hears about first: it is why the ring went back.
  const missing = msg.missing || [];
  const next = missing.find((m) => m.undone) || missing[0];
  showChips(joints, next ? next.joint : null);
  setProgress(msg.progress, msg.percent, msg.fit_seq);
  if (msg.done) {
    finishGuest();
    return;
  }
  const el = $('instruction');
  el.dataset.why = next && next.undone ? 'undone' : (msg.prompt ? 'stalled' : 'next');
  if (next && next.undone) el.textContent = instructionFor(next);
  else if (msg.prompt) el.textContent = msg.prompt;
  else if (next) el.textContent = instructionFor(next);
}

// Avatar joints: green when calibrated, amber while pinned but not counted yet, grey while undetermined.
function jointColour(j) {
  if (j.done) return 'done';
  return ['pinning', 'confirming', 'unsettled'].includes(j.state) ? 'work' : 'none';
}

function clearTimer() { if (kiosk.timer) { clearTimeout(kiosk.timer); kiosk.timer = null; } }

function follow(session, owned) {
  kiosk.session = session;
  kiosk.owned = owned;
  keepLease(owned ? session : null);  // a reloaded page takes over renewing its guest's session
  kiosk.startedAt = performance.now();
  setProgress(0, 0, null);
  $('chips').innerHTML = '';
  setState('live', owned ? 'calibrating — keep moving!' : `calibrating ${session.performer}`);
  $('instruction').textContent = 'Wave your arms and march on the spot!';
}

async function startGuest() {
  clearTimer();
  if (!kiosk.canControl) { waitForHost(); return; }
  setState('starting', 'getting ready…');
  setProgress(0, 0, null);
  try {
    const stamp = new Date().toTimeString().slice(0, 8).replace(/:/g, '.');
    const s = await api('/api/sessions', { method: 'POST',
      json: { performer: `guest ${stamp}`, profile: 'kiosk', lease_s: LEASE_S } });
    follow({ id: s.id, performer: s.performer }, true);
  } catch (err) {
    if (err instanceof ApiError && (err.status === 403 || err.status === 401)) {
      // A read-only token: this kiosk shows the sessions a host starts.
      kiosk.canControl = false;
      waitForHost();
      return;
    }
    const live = kiosk.lastStatus && kiosk.lastStatus.session;
    if (err instanceof ApiError && err.status === 409) {
      // A session started between the last status and this request: a guest's is taken over, an
      // operator's waited out on a clear screen (never shown as this guest's).
      if (live && isGuestSession(live)) follow(live, true);
      else stageInUse();
      return;
    }
    setState('error', `waiting for the calibration service (${err.message})`);
    kiosk.timer = setTimeout(startGuest, 3000);
  }
}

function waitForHost() {
  const live = kiosk.lastStatus && kiosk.lastStatus.session;
  if (live) { follow(live, false); return; }
  setState('waiting', 'waiting for the host to start your calibration');
  setProgress(0, 0, null);
  $('instruction').textContent = 'Welcome! A host will start your calibration in a moment.';
}

async function finishGuest() {
  const session = kiosk.session;
  setState('done', 'done!');
  $('instruction').textContent = "You're all set — enjoy the show!";
  avatar.setJointState(Object.fromEntries(Object.keys(avatar.jointState).map((k) => [k, 'done'])));
  $('chips').querySelectorAll('.chip').forEach((c) => { c.className = 'chip done'; c.textContent = `✓ ${part(c.dataset.body)}`; });
  clearTimer();
  if (session && !kiosk.owned) {
    // A host's session: it is theirs to stop. Stay "done" until it ends, then wait for the next.
    kiosk.doneSession = session.id;
    $('kiosk-state').textContent = `done! ${session.performer} is calibrated`;
    return;
  }
  if (session) {
    try { await api(`/api/sessions/${encodeURIComponent(session.id)}/stop`, { method: 'POST' }); } catch (e) { /* already stopped */ }
  }
  kiosk.session = null;
  const until = performance.now() + RESET_S * 1000;
  const countdown = () => {
    const left = Math.ceil((until - performance.now()) / 1000);
    if (left <= 0) { startGuest(); return; }
    $('kiosk-state').textContent = `done! next guest in ${left} s`;
    kiosk.timer = setTimeout(countdown, 250);
  };
  countdown();
}

async function giveUp() {
  // The guest walked away before finishing: end their session and start afresh.
  const session = kiosk.session;
  if (session && kiosk.owned) {
    try { await api(`/api/sessions/${encodeURIComponent(session.id)}/stop`, { method: 'POST' }); } catch (e) { /* gone */ }
  }
  kiosk.session = null;
  startGuest();
}

function onStatus(s) {
  kiosk.lastStatus = s;
  const trackerOk = !!s.connected;
  const el = $('kiosk-state');
  el.dataset.tracker = trackerOk ? 'connected' : 'disconnected';
  showBanner();
  const live = s.session || null;
  if (kiosk.state === 'live' && kiosk.session && (!live || live.id !== kiosk.session.id)) {
    // The session ended without us (service restarted, host stopped it): next guest.
    kiosk.session = null;
    if (live && !kiosk.canControl) follow(live, false);
    else if (live && !isGuestSession(live)) stageInUse();  // an operator took the stage meanwhile
    else { clearTimer(); kiosk.timer = setTimeout(startGuest, 500); setState('starting', 'getting ready…'); }
  } else if (kiosk.state === 'waiting' && live) {
    follow(live, false);
  } else if (kiosk.state === 'busy' && !live) {
    startGuest();  // the operator's session ended: the stage is the guests' again
  } else if (kiosk.state === 'done' && kiosk.doneSession && (!live || live.id !== kiosk.doneSession)) {
    kiosk.doneSession = null;
    kiosk.session = null;
    waitForHost();
  } else if (kiosk.state === 'live' && kiosk.owned && performance.now() - kiosk.startedAt > MAX_S * 1000) {
    giveUp();
  }
}

let linkState = 'connecting';
function showBanner() {
  const b = $('banner');
  const s = kiosk.lastStatus;
  let text = '';
  if (linkState === 'unauthorised') text = 'This kiosk needs its token: open /kiosk?token=…';
  else if (linkState !== 'open') text = 'Reconnecting to the calibration service…';
  else if (s && !s.connected) text = 'The tracker is disconnected — please ask a host for help.';
  b.textContent = text;
  b.classList.toggle('hidden', !text);
  $('kiosk-state').dataset.link = linkState;
}

let started = false;
connectLive({
  content: ['status', 'fit', 'pose'],
  rateHz: 20,
  onState: (st) => { linkState = st; showBanner(); },
  onMessage: (msg) => {
    if (msg.type === 'hello' || msg.type === 'subscribed') {
      // The token's role, before anything is tried: a read-only kiosk follows a host's sessions.
      if (msg.role) kiosk.canControl = msg.role !== 'read';
    } else if (msg.type === 'status') {
      onStatus(msg.status);
      if (!started) { started = true; startOrWait(); }
    } else if (msg.type === 'fit') onFit(msg);
    else if (msg.type === 'pose' && msg.pose && kiosk.state !== 'busy') avatar.update(msg.pose);
  },
});
