// Shared by the operator dashboard and the kiosk: REST and websocket access with automatic
// reconnection, readable body and joint names, and the 3D skeleton view: the session's glTF rig
// (rig.js) driven by the live pose once there is a fit, the pose's own points and bones before that,
// a 2D drawing without WebGL.

import * as THREE from './vendor/three/three.module.js';
import { OrbitControls } from './vendor/three/OrbitControls.js';
import { parseRig, rigPath } from './rig.js';
import { BODY_JOINTS, BONE_WORDS } from './names.js'; // made by the service from flockcal/names.py

// A token given once as ?token=… is kept for the tab, so reloads and reconnects keep working.
const params = new URLSearchParams(location.search);
if (params.get('token')) sessionStorage.setItem('flockcal-token', params.get('token'));
export const token = sessionStorage.getItem('flockcal-token') || '';

export class ApiError extends Error {
  constructor(status, message) { super(message); this.status = status; }
}

export async function api(path, options = {}) {
  const headers = Object.assign({ Accept: 'application/json' }, options.headers || {});
  if (token) headers.Authorization = `Bearer ${token}`;
  const init = Object.assign({}, options, { headers });
  if (options.json !== undefined) {
    headers['Content-Type'] = 'application/json';
    init.body = JSON.stringify(options.json);
    delete init.json;
  }
  let response;
  try {
    response = await fetch(path, init);
  } catch (e) {
    throw new ApiError(0, 'the flockcal service is not reachable');
  }
  if (options.raw) {
    if (!response.ok) throw new ApiError(response.status, `${response.status} ${response.statusText}`);
    return response;
  }
  const text = await response.text();
  let body = null;
  try { body = text ? JSON.parse(text) : null; } catch (e) { body = text; }
  if (!response.ok) {
    const detail = body && (body.detail || body.message || body.error);
    throw new ApiError(response.status, typeof detail === 'string' ? detail : `${response.status} ${response.statusText}`);
  }
  return body;
}

// Downloads go through fetch so the bearer token travels in a header, never in a link.
export async function download(path, filename) {
  const response = await api(path, { raw: true });
  const url = URL.createObjectURL(await response.blob());
  const a = document.createElement('a');
  a.href = url;
  a.download = filename;
  document.body.appendChild(a);
  a.click();
  a.remove();
  setTimeout(() => URL.revokeObjectURL(url), 10000);
}

// Body names arrive as "l_forearm", "RightUpLeg", "bird3"; people read "left forearm".
// Mirrors flockcal.names.readable_body so page and hints agree.
export function readable(name) {
  if (!name) return '';
  const s = String(name).replace(/([a-z])([A-Z])/g, '$1 $2').replace(/([A-Za-z])(\d)/g, '$1 $2');
  const words = s.split(/[\s_.-]+/).filter(Boolean);
  let out = words.map((w, k) => {
    const lw = w.toLowerCase();
    const edge = k === 0 || k === words.length - 1;
    if (edge && (lw === 'l' || lw === 'lt')) return 'left';
    if (edge && (lw === 'r' || lw === 'rt')) return 'right';
    return lw;
  });
  if (out.length > 1 && (out[out.length - 1] === 'left' || out[out.length - 1] === 'right')) {
    out = [out[out.length - 1]].concat(out.slice(0, -1));
  }
  return out.join(' ');
}

function bodyJoint(name) {
  let body = readable(name);
  let side = '';
  for (const s of ['left ', 'right ']) if (body.startsWith(s)) { side = s; body = body.slice(s.length); }
  for (const [re, joint, rank] of BODY_JOINTS) if (re.test(body)) return { label: `${side}${joint}`, rank };
  return null;
}

// The joint between two bodies as people name it ("left elbow"), the same whichever body the fit
// made the child (design.md §5 names a joint by its child); unknown bodies give "parent–child".
export function jointLabel(child, parent) {
  const a = bodyJoint(child);
  const b = parent ? bodyJoint(parent) : null;
  if (a && (!b || a.rank >= b.rank)) return a.label;
  if (b && parent) return b.label;
  return parent ? `${readable(parent)}–${readable(child)}` : readable(child);
}

// The body a sensor was found on ("left forearm"): the fit's humanoid (design.md §5 `humanoid`, found from
// the data whatever the sensor is called), else the sensor's own name read as words.
export function foundOn(fit, sensor) {
  const bone = fit && fit.humanoid && fit.humanoid[sensor];
  return bone ? (BONE_WORDS[bone] || bone) : readable(sensor);
}

// A joint named by its child as the fit names it (`joints[].name`: "left knee", "lower back"), else as the
// two bodies' names say (jointLabel).
export function jointName(fit, child, parent) {
  const j = fit && (fit.joints || []).find((x) => x.child === child);
  if (j && j.name) return j.name;
  const p = parent !== undefined ? parent : fit && fit.parent && fit.parent[child];
  return jointLabel(child, p);
}

// The live websocket: subscribes on every (re)connection and backs off up to 4 s between tries, so
// the page recovers by itself after the server restarts. onState gets 'connecting' | 'open' |
// 'closed' | 'unauthorised'.
export function connectLive({ content, rateHz = 15, onMessage, onState }) {
  let socket = null;
  let delay = 250;
  let closed = false;
  let lastSeq = -1;
  let refused = false;
  const url = () => {
    const proto = location.protocol === 'https:' ? 'wss' : 'ws';
    const q = token ? `?token=${encodeURIComponent(token)}` : '';
    return `${proto}://${location.host}/ws/live${q}`;
  };
  const open = () => {
    if (closed) return;
    onState && onState('connecting');
    refused = false;
    socket = new WebSocket(url());
    socket.onopen = () => {
      delay = 250;
      lastSeq = -1;  // a new connection numbers its messages from 1 again
      socket.send(JSON.stringify({ type: 'subscribe', rate_hz: rateHz, content, token: token || undefined }));
      onState && onState('open');
    };
    socket.onmessage = (ev) => {
      let msg;
      try { msg = JSON.parse(ev.data); } catch (e) { return; }
      if (typeof msg.seq === 'number') {
        if (msg.seq <= lastSeq) return;  // never go backwards
        lastSeq = msg.seq;
      }
      if (msg.type === 'error' && /token/.test(msg.message || '')) refused = true;
      onMessage(msg);
    };
    socket.onclose = (ev) => {
      const unauthorised = refused || ev.code === 1008;
      onState && onState(unauthorised ? 'unauthorised' : 'closed');
      if (closed) return;
      setTimeout(open, unauthorised ? 5000 : delay);
      delay = Math.min(delay * 2, 4000);
    };
    socket.onerror = () => { try { socket.close(); } catch (e) { /* closing anyway */ } };
  };
  open();
  return { close() { closed = true; if (socket) socket.close(); } };
}

// Tracker coordinates are the Flock of Birds frame (+X forward, +Y right, +Z down, metres);
// three.js wants +Y up. (x, y, z) -> (y, -z, -x) keeps the frame right-handed.
function toView(p) { return new THREE.Vector3(p[1], -p[2], -p[0]); }

function hasWebGL() {
  try {
    const c = document.createElement('canvas');
    return !!(c.getContext('webgl2') || c.getContext('webgl'));
  } catch (e) { return false; }
}

// The server's pose message → {joints: [{name, kind, p}], bones: [[a, b]], sensors: [{name, p, R, valid}]}.
export function normalisePose(msg) {
  const src = msg.pose || msg;
  const joints = (src.joints || []).map((j) => ({ name: j.name || '', kind: j.kind || 'joint', p: j.p }));
  const sensors = (src.sensors || []).map((s) => ({ name: s.name, p: s.p, R: s.R, valid: s.valid !== false }));
  const bones = (src.bones || []).filter((b) => Array.isArray(b) && b.length === 2);
  return { joints, bones, sensors, root: src.root || null, rig: src.rig || null };
}

// Where the fitted model puts each sensor: its body's joint centre minus R·c (c = that joint in the
// sensor's frame), so the boxes ride on the residual-free skeleton; the root sensor and bodies
// without a fitted joint stay where they were measured.
function modelSensors(pose, placement) {
  const pivot = {};
  for (const j of pose.joints) if (j.kind !== 'end' && j.p) pivot[j.name] = j.p;
  return pose.sensors.map((s) => {
    const c = placement && placement[s.name];
    const p0 = pivot[s.name];
    if (!c || !p0 || !s.R || s.R.length !== 9 || pose.root === s.name) return s;
    const R = s.R;
    const p = [0, 1, 2].map((r) => p0[r] - (R[3 * r] * c[0] + R[3 * r + 1] * c[1] + R[3 * r + 2] * c[2]));
    return Object.assign({}, s, { p, fitted: true });
  });
}

const BG = 0x0d1117;
const STATE_COLOURS = { done: 0x3fb950, work: 0xffc857, none: 0x6e7681 };
// A live session's fit changes many times a second: its rig is fetched again at most this often (a new
// session's, or a stopped session's final fit, at once); a failed fetch is tried again after RIG_RETRY_MS.
const RIG_RELOAD_MS = 2000;
const RIG_RETRY_MS = 5000;

export class SkeletonView {
  // follow: keep the camera on the performer and in front of them (kiosk); otherwise it is aimed
  // once and left to the operator's orbit.
  // mirror: show the performer as in a mirror (their left on the screen's left), for guests facing it.
  constructor(container, { colour = 0x3fa9f5, follow = false, mirror = false, background = BG } = {}) {
    this.container = container;
    this.mirror = mirror;
    this.colour = colour;
    this.follow = follow;
    this.background = background;
    this.webgl = hasWebGL();
    this.centre = null;
    this.placement = null;   // {body: c} from the newest fit
    this.jointState = {};    // {body: 'done' | 'work' | 'none'} colours the joint spheres
    this.frames = 0;         // poses drawn (tests and the status line read it)
    this.rig = null;         // the loaded glTF rig (rig.js LoadedRig), null before the first fit
    this.rigLoading = false;
    this.rigLoadedAt = -Infinity;
    this.rigRetryAt = 0;
    this.rigShown = null;    // {rig, pose}: the rig last drawn and the pose message it was set from
    container.dataset.renderer = this.webgl ? 'webgl' : '2d';
    container.dataset.rig = 'none';
    if (this.webgl) this._initThree(); else this._init2d();
    new ResizeObserver(() => this.resize()).observe(container);
    this.resize();
    // A small debugging hook (docs/dashboard.md, "The skeleton view"): what the view drew from the rig and
    // three.js's own joint positions for it, for the console and the browser tests.
    const view = this;
    window.flockcalRig = {
      get state() { return view.container.dataset.rig; },
      get session() { return view.rigShown ? view.rigShown.rig.session : null; },
      get fitSeq() { return view.rigShown ? view.rigShown.rig.fitSeq : null; },
      get pose() { return view.rigShown ? view.rigShown.pose : null; },
      get error() { return view.rigError || null; },
      joints() { return view.rigShown ? view.rigShown.rig.jointPositions() : null; },
      sensors() { return view.rigShown ? view.rigShown.rig.sensorOf : null; },
    };
  }

  setFit(result) {
    const placement = {};
    for (const j of (result && result.joints) || []) if (j.c && j.c.every(Number.isFinite)) placement[j.child] = j.c;
    this.placement = placement;
  }

  setJointState(state) { this.jointState = state || {}; this.dirty = true; }

  _initThree() {
    this.renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
    this.renderer.setPixelRatio(Math.min(window.devicePixelRatio || 1, 2));
    this.container.appendChild(this.renderer.domElement);
    this.renderer.domElement.classList.add('skeleton-canvas');
    this.scene = new THREE.Scene();
    this.scene.background = new THREE.Color(this.background);
    // Everything drawn hangs from one group, so a mirror is one negative scale (three.js flips the
    // face winding for it) and the camera maths below works in the same mirrored world.
    this.world = new THREE.Group();
    if (this.mirror) this.world.scale.x = -1;
    this.scene.add(this.world);
    this.camera = new THREE.PerspectiveCamera(40, 1, 0.01, 50);
    this.camera.position.set(1.6, 1.2, 2.4);
    this.controls = new OrbitControls(this.camera, this.renderer.domElement);
    this.controls.enableDamping = true;
    this.controls.addEventListener('change', () => { this.dirty = true; });
    this.scene.add(new THREE.HemisphereLight(0xffffff, 0x2a3440, 2.4));
    const sun = new THREE.DirectionalLight(0xffffff, 1.6);
    sun.position.set(2, 4, 3);
    this.scene.add(sun);
    this.grid = new THREE.GridHelper(4, 16, 0x30363d, 0x1c2128);
    this.world.add(this.grid);
    this.mats = {};
    for (const [k, c] of Object.entries(STATE_COLOURS)) this.mats[k] = new THREE.MeshStandardMaterial({ color: c, roughness: 0.35 });
    this.boneMat = new THREE.MeshStandardMaterial({ color: this.colour, roughness: 0.45 });
    this.sensorMat = new THREE.MeshStandardMaterial({ color: 0xe4572e, roughness: 0.6 });
    this.sensorOffMat = new THREE.MeshStandardMaterial({ color: 0x484f58, roughness: 0.8 });
    this.jointGeo = new THREE.SphereGeometry(0.03, 20, 14);
    this.endGeo = new THREE.SphereGeometry(0.018, 14, 10);
    this.boneGeo = new THREE.CylinderGeometry(0.014, 0.014, 1, 12);
    this.sensorGeo = new THREE.BoxGeometry(0.04, 0.022, 0.05);
    this.meshes = { joints: [], bones: [], sensors: [] };
    this.dirty = true;
    // Draw only when something changed: the pose arrives 15–20 times a second, and a kiosk PC or a
    // software renderer should not spend a core redrawing an unchanged scene.
    const tick = () => {
      this.controls.update();
      if (this.dirty) {
        this.dirty = false;
        this.renderer.render(this.scene, this.camera);
      }
      requestAnimationFrame(tick);
    };
    tick();
  }

  _init2d() {
    // Without WebGL (old kiosk PCs, remote desktops) draw an orthographic projection that still orbits.
    this.canvas = document.createElement('canvas');
    this.canvas.classList.add('skeleton-canvas');
    this.container.appendChild(this.canvas);
    this.yaw = 0.6; this.pitch = 0.25;
    let dragging = null;
    this.canvas.addEventListener('pointerdown', (e) => { dragging = [e.clientX, e.clientY]; });
    window.addEventListener('pointerup', () => { dragging = null; });
    window.addEventListener('pointermove', (e) => {
      if (!dragging) return;
      this.yaw += (e.clientX - dragging[0]) * 0.01;
      this.pitch = Math.max(-1.4, Math.min(1.4, this.pitch + (e.clientY - dragging[1]) * 0.01));
      dragging = [e.clientX, e.clientY];
      this._draw2d();
    });
  }

  resize() {
    const w = this.container.clientWidth || 400;
    const h = this.container.clientHeight || 300;
    if (this.webgl) {
      this.renderer.setSize(w, h);
      this.camera.aspect = w / h;
      this.camera.updateProjectionMatrix();
      this.dirty = true;
    } else {
      this.canvas.width = w; this.canvas.height = h;
      this._draw2d();
    }
  }

  _pool(kind, n, make) {
    const list = this.meshes[kind];
    while (list.length < n) { const m = make(); this.world.add(m); list.push(m); }
    list.forEach((m, i) => { m.visible = i < n; });
    return list;
  }

  // The direction the performer faces (view coordinates), from left/right named bodies; null if unnamed.
  _facing(pose) {
    const left = new THREE.Vector3(), right = new THREE.Vector3();
    let nl = 0, nr = 0;
    for (const j of pose.joints) {
      if (!j.p || j.kind === 'end') continue;
      const r = readable(j.name);
      if (r.startsWith('left ')) { left.add(toView(j.p)); nl += 1; }
      if (r.startsWith('right ')) { right.add(toView(j.p)); nr += 1; }
    }
    if (!nl || !nr) return null;
    const lateral = left.divideScalar(nl).sub(right.divideScalar(nr));
    lateral.y = 0;
    if (lateral.lengthSq() < 1e-6) return null;
    // left = up × forward, so forward = left × up.
    return lateral.normalize().cross(new THREE.Vector3(0, 1, 0)).normalize();
  }

  // The rig the pose's `rig` is for: fetched when there is none, when the session changes, when a session's
  // final fit replaces its live one, and at most every RIG_RELOAD_MS while a live fit moves on.
  _fetchRig(want) {
    if (this.rigLoading || performance.now() < this.rigRetryAt) return;
    const have = this.rig;
    const seq = want.fit_seq === undefined ? null : want.fit_seq;
    if (have && have.session === want.session) {
      const since = performance.now() - this.rigLoadedAt;
      if (have.fitSeq === seq) { if (have.fits(want) || since < RIG_RETRY_MS) return; }
      else if (seq !== null && since < RIG_RELOAD_MS) return;
    }
    this.rigLoading = true;
    this.rigLoadedAt = performance.now();
    if (!this.rigShown) this.container.dataset.rig = 'loading';
    (async () => {
      const response = await api(rigPath(want.session), { raw: true });
      const header = response.headers.get('X-Flockcal-Fit-Seq');
      const fitSeq = header === null || header === 'final' ? null : Number(header);
      return parseRig(await response.arrayBuffer(), want.session, fitSeq,
                      { colour: this.colour, markers: { geometry: this.jointGeo, endGeometry: this.endGeo } });
    })().then((rig) => {
      if (this.rig && !(this.rigShown && this.rigShown.rig === this.rig)) this.rig.dispose();
      this.rig = rig;
      rig.holder.visible = false;  // until a pose sets it
      this.world.add(rig.holder);
      this.rigError = null;
    }, (e) => {
      this.rigError = (e && e.message) || String(e);
      this.rigRetryAt = performance.now() + RIG_RETRY_MS;
      if (!this.rigShown) this.container.dataset.rig = 'failed';
    }).finally(() => { this.rigLoading = false; });
  }

  // Draw the pose with the rig when the loaded one is the pose's tree; false: draw the fallback instead.
  _drawRig(poseMsg, pose) {
    const want = pose.rig;
    if (!want || !want.session) return this._hideRig('none');  // no fit yet: nothing to load
    this._fetchRig(want);
    const rig = this.rig;
    if (!rig || !rig.fits(want)) return this._hideRig(this.rigLoading ? 'loading' : (this.rigError ? 'failed' : 'waiting'));
    rig.apply(want, (kind, sensor) => this.mats[kind === 'end' || kind === 'root' ? 'done' : (this.jointState[sensor] || 'work')] || this.mats.work);
    rig.holder.visible = true;
    if (this.rigShown && this.rigShown.rig !== rig) this.rigShown.rig.dispose();
    this.rigShown = { rig, pose: poseMsg };
    const seq = want.fit_seq === undefined ? null : want.fit_seq;
    this.container.dataset.rig = 'shown';
    this.container.dataset.rigSession = rig.session;
    this.container.dataset.rigFitSeq = rig.fitSeq === null ? 'final' : String(rig.fitSeq);
    this.container.dataset.rigCurrent = String(rig.fitSeq === seq);
    return true;
  }

  _hideRig(state) {
    if (this.rigShown && this.rigShown.rig !== this.rig) this.rigShown.rig.dispose();
    if (this.rig) this.rig.holder.visible = false;
    this.rigShown = null;
    this.container.dataset.rig = state;
    return false;
  }

  update(poseMsg) {
    const pose = normalisePose(poseMsg);
    pose.sensors = modelSensors(pose, this.placement);
    this.pose = pose;
    this.frames += 1;
    this.container.dataset.frames = this.frames;
    this.container.dataset.joints = pose.joints.length;
    const pts = pose.joints.filter((j) => j.p).map((j) => toView(j.p));
    if (!pts.length) pose.sensors.forEach((s) => { if (s.p) pts.push(toView(s.p)); });
    if (this.mirror) pts.forEach((p) => { p.x = -p.x; });
    if (pts.length) {
      const c = new THREE.Vector3();
      pts.forEach((p) => c.add(p));
      c.divideScalar(pts.length);
      let low = Infinity;
      pts.forEach((p) => { low = Math.min(low, p.y); });
      if (!this.centre) {
        // Aim the camera once at the performer, from the front-left; the operator's orbit is then left alone.
        this.centre = c.clone();
        if (this.webgl) {
          const f = this._facing(pose) || new THREE.Vector3(0, 0, 1);
          if (this.mirror) f.x = -f.x;
          const side = new THREE.Vector3(0, 1, 0).cross(f).normalize();
          this.controls.target.copy(c);
          const dist = this.follow ? 2.9 : 2.2;
          const sideways = this.follow ? 0.25 : 0.7;
          this.camera.position.copy(c).addScaledVector(f, dist).addScaledVector(side, sideways * dist).add(new THREE.Vector3(0, 0.5, 0));
          this.grid.position.set(this.mirror ? -c.x : c.x, low - 0.04, c.z);
        }
      } else if (this.follow && this.webgl) {
        // Glide after the guest: the target eases towards them, the camera keeps its offset.
        const shift = c.clone().sub(this.controls.target).multiplyScalar(0.15);
        this.controls.target.add(shift);
        this.camera.position.add(shift);
        this.grid.position.set((this.mirror ? -1 : 1) * this.controls.target.x, low - 0.04, this.controls.target.z);
      }
    }
    if (!this.webgl) { this._draw2d(); return; }
    // With the rig drawn, the pose's own points and bones step aside; the sensors stay either way.
    const named = this._drawRig(poseMsg, pose) ? [] : pose.joints;
    const joints = this._pool('joints', named.length, () => new THREE.Mesh(this.jointGeo, this.mats.work));
    named.forEach((j, i) => {
      const m = joints[i];
      if (!j.p) { m.visible = false; return; }
      m.position.copy(toView(j.p));
      m.geometry = j.kind === 'end' ? this.endGeo : this.jointGeo;
      const st = j.kind === 'end' || j.kind === 'root' ? 'done' : (this.jointState[j.name] || 'work');
      m.material = this.mats[st] || this.mats.work;
    });
    const boneList = named.length ? pose.bones : [];
    const bones = this._pool('bones', boneList.length, () => new THREE.Mesh(this.boneGeo, this.boneMat));
    const up = new THREE.Vector3(0, 1, 0);
    boneList.forEach(([a, b], i) => {
      const pa = named[a] && named[a].p, pb = named[b] && named[b].p;
      if (!pa || !pb) { bones[i].visible = false; return; }
      const va = toView(pa), vb = toView(pb);
      const d = vb.clone().sub(va);
      const len = d.length();
      bones[i].position.copy(va).add(vb).multiplyScalar(0.5);
      bones[i].scale.set(1, Math.max(len, 1e-4), 1);
      bones[i].quaternion.setFromUnitVectors(up, len > 0 ? d.normalize() : up);
    });
    const sensors = this._pool('sensors', pose.sensors.length, () => new THREE.Mesh(this.sensorGeo, this.sensorMat));
    pose.sensors.forEach((s, i) => {
      if (!s.p) { sensors[i].visible = false; return; }
      sensors[i].position.copy(toView(s.p));
      sensors[i].material = s.valid ? this.sensorMat : this.sensorOffMat;
      if (s.R && s.R.length === 9) {
        // Sensor axes in tracker coordinates, mapped to view axes the same way as positions.
        const R = s.R;
        const col = (k) => toView([R[k], R[3 + k], R[6 + k]]);
        sensors[i].quaternion.setFromRotationMatrix(new THREE.Matrix4().makeBasis(col(0), col(1), col(2)));
      }
    });
    this.dirty = true;
  }

  _draw2d() {
    const ctx = this.canvas.getContext('2d');
    const w = this.canvas.width, h = this.canvas.height;
    ctx.fillStyle = '#0d1117';
    ctx.fillRect(0, 0, w, h);
    if (!this.pose) return;
    const cy = Math.cos(this.yaw), sy = Math.sin(this.yaw), cp = Math.cos(this.pitch), sp = Math.sin(this.pitch);
    const c = this.centre || new THREE.Vector3();
    const project = (p) => {
      const v = toView(p).sub(c);
      const x = cy * v.x + sy * v.z, z = -sy * v.x + cy * v.z;
      const y = cp * v.y - sp * z;
      const s = Math.min(w, h) / 2.2;
      return [w / 2 + x * s, h / 2 - y * s];
    };
    ctx.strokeStyle = '#' + this.colour.toString(16).padStart(6, '0'); ctx.lineWidth = 4;
    this.pose.bones.forEach(([a, b]) => {
      const pa = this.pose.joints[a] && this.pose.joints[a].p, pb = this.pose.joints[b] && this.pose.joints[b].p;
      if (!pa || !pb) return;
      const [x1, y1] = project(pa), [x2, y2] = project(pb);
      ctx.beginPath(); ctx.moveTo(x1, y1); ctx.lineTo(x2, y2); ctx.stroke();
    });
    this.pose.joints.forEach((j) => {
      if (!j.p) return;
      const st = j.kind === 'end' || j.kind === 'root' ? 'done' : (this.jointState[j.name] || 'work');
      ctx.fillStyle = '#' + STATE_COLOURS[st].toString(16).padStart(6, '0');
      const [x, y] = project(j.p); ctx.beginPath(); ctx.arc(x, y, 5, 0, 7); ctx.fill();
    });
    ctx.fillStyle = '#e4572e';
    this.pose.sensors.forEach((s) => { if (!s.p) return; const [x, y] = project(s.p); ctx.fillRect(x - 4, y - 4, 8, 8); });
  }
}
