// Shared by the operator dashboard and the kiosk: REST and websocket access with automatic
// reconnection, readable body names, and the 3D skeleton view (three.js, 2D canvas fallback).

import * as THREE from './vendor/three/three.module.js';
import { OrbitControls } from './vendor/three/OrbitControls.js';

// A token given once as ?token=… is kept for the tab, so reloads and reconnects keep working.
const params = new URLSearchParams(location.search);
if (params.get('token')) sessionStorage.setItem('flockcal-token', params.get('token'));
export const token = sessionStorage.getItem('flockcal-token') || '';

export async function api(path, options = {}) {
  const headers = Object.assign({ 'Accept': 'application/json' }, options.headers || {});
  if (token) headers['Authorization'] = `Bearer ${token}`;
  if (options.json !== undefined) {
    headers['Content-Type'] = 'application/json';
    options.body = JSON.stringify(options.json);
  }
  const response = await fetch(path, Object.assign({}, options, { headers }));
  const text = await response.text();
  let body = null;
  try { body = text ? JSON.parse(text) : null; } catch (e) { body = text; }
  if (!response.ok) {
    const detail = body && (body.message || body.detail || body.error);
    const message = typeof detail === 'string' ? detail : JSON.stringify(detail || body);
    throw new Error(`${response.status}: ${message}`);
  }
  return body;
}

// Body names arrive as snake_case ("l_forearm"); people read "left forearm".
export function readable(name) {
  if (!name) return '';
  return String(name)
    .replace(/^l_/, 'left ').replace(/^r_/, 'right ')
    .replace(/_l$/, ' (left)').replace(/_r$/, ' (right)')
    .replace(/_/g, ' ');
}

// The live websocket: subscribes on every (re)connection and backs off up to 5 s between tries, so
// the page recovers by itself after the server restarts.
export function connectLive({ content, rateHz = 15, onMessage, onState }) {
  let socket = null;
  let delay = 250;
  let closed = false;
  let lastSeq = -1;
  const url = () => {
    const proto = location.protocol === 'https:' ? 'wss' : 'ws';
    const q = token ? `?token=${encodeURIComponent(token)}` : '';
    return `${proto}://${location.host}/ws/live${q}`;
  };
  const open = () => {
    if (closed) return;
    onState && onState('connecting');
    socket = new WebSocket(url());
    socket.onopen = () => {
      delay = 250;
      lastSeq = -1;
      socket.send(JSON.stringify({ type: 'subscribe', rate_hz: rateHz, content, token }));
      onState && onState('open');
    };
    socket.onmessage = (ev) => {
      let msg;
      try { msg = JSON.parse(ev.data); } catch (e) { return; }
      if (typeof msg.seq === 'number') {
        if (msg.seq <= lastSeq) return;  // never go backwards
        lastSeq = msg.seq;
      }
      onMessage(msg);
    };
    socket.onclose = () => {
      onState && onState('closed');
      if (closed) return;
      setTimeout(open, delay);
      delay = Math.min(delay * 2, 5000);
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

// Accepts the server's "pose" message and returns {joints: [{name, p}], bones: [[a, b]], sensors: [{name, p, R}]}.
export function normalisePose(msg) {
  const src = msg.pose || msg;
  let joints = src.joints || [];
  if (!Array.isArray(joints)) joints = Object.entries(joints).map(([name, p]) => ({ name, p }));
  joints = joints.map((j) => (Array.isArray(j) ? { name: '', p: j } : { name: j.name || j.child || '', p: j.p || j.position }));
  let sensors = src.sensors || [];
  if (!Array.isArray(sensors)) sensors = Object.entries(sensors).map(([name, s]) => Object.assign({ name }, s));
  sensors = sensors.map((s) => ({ name: s.name, p: s.p || s.position, R: s.R || s.rotation }));
  const bones = (src.bones || []).map((b) => (Array.isArray(b) ? b : [b.from ?? b.a, b.to ?? b.b]));
  return { joints, bones, sensors };
}

export class SkeletonView {
  constructor(container, { autoRotate = false, colour = 0x3fa9f5 } = {}) {
    this.container = container;
    this.colour = colour;
    this.webgl = hasWebGL();
    this.centre = null;
    if (this.webgl) this._initThree(autoRotate); else this._init2d();
    window.addEventListener('resize', () => this.resize());
    this.resize();
  }

  _initThree(autoRotate) {
    this.renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
    this.renderer.setPixelRatio(window.devicePixelRatio || 1);
    this.container.appendChild(this.renderer.domElement);
    this.renderer.domElement.classList.add('skeleton-canvas');
    this.scene = new THREE.Scene();
    this.scene.background = new THREE.Color(0x10141a);
    this.camera = new THREE.PerspectiveCamera(45, 1, 0.01, 50);
    this.camera.position.set(1.6, 1.2, 2.4);
    this.controls = new OrbitControls(this.camera, this.renderer.domElement);
    this.controls.enableDamping = true;
    this.controls.autoRotate = autoRotate;
    this.controls.autoRotateSpeed = 1.0;
    this.scene.add(new THREE.HemisphereLight(0xffffff, 0x334455, 2.2));
    const sun = new THREE.DirectionalLight(0xffffff, 1.5);
    sun.position.set(2, 4, 3);
    this.scene.add(sun);
    const grid = new THREE.GridHelper(4, 20, 0x2b3440, 0x1d242d);
    this.grid = grid;
    this.scene.add(grid);
    this.jointMat = new THREE.MeshStandardMaterial({ color: 0xffc857, roughness: 0.4 });
    this.boneMat = new THREE.MeshStandardMaterial({ color: this.colour, roughness: 0.5 });
    this.sensorMat = new THREE.MeshStandardMaterial({ color: 0xe4572e, roughness: 0.6 });
    this.jointGeo = new THREE.SphereGeometry(0.025, 16, 12);
    this.boneGeo = new THREE.CylinderGeometry(0.012, 0.012, 1, 10);
    this.sensorGeo = new THREE.BoxGeometry(0.035, 0.02, 0.045);
    this.meshes = { joints: [], bones: [], sensors: [] };
    const tick = () => {
      this.controls.update();
      this.renderer.render(this.scene, this.camera);
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
    } else {
      this.canvas.width = w; this.canvas.height = h;
      this._draw2d();
    }
  }

  _pool(kind, n, make) {
    const list = this.meshes[kind];
    while (list.length < n) { const m = make(); this.scene.add(m); list.push(m); }
    list.forEach((m, i) => { m.visible = i < n; });
    return list;
  }

  update(poseMsg) {
    const pose = normalisePose(poseMsg);
    this.pose = pose;
    const pts = pose.joints.filter((j) => j.p).map((j) => toView(j.p));
    if (pts.length && !this.centre) {
      // Aim the camera once at the performer; after that the operator's orbit is left alone.
      const c = new THREE.Vector3();
      pts.forEach((p) => c.add(p));
      c.divideScalar(pts.length);
      this.centre = c;
      if (this.webgl) {
        this.controls.target.copy(c);
        this.camera.position.set(c.x + 1.6, c.y + 0.6, c.z + 2.2);
        let low = Infinity;
        pts.forEach((p) => { low = Math.min(low, p.y); });
        this.grid.position.set(c.x, low - 0.05, c.z);
      }
    }
    if (!this.webgl) { this._draw2d(); return; }
    const joints = this._pool('joints', pose.joints.length, () => new THREE.Mesh(this.jointGeo, this.jointMat));
    pose.joints.forEach((j, i) => { if (j.p) joints[i].position.copy(toView(j.p)); });
    const bones = this._pool('bones', pose.bones.length, () => new THREE.Mesh(this.boneGeo, this.boneMat));
    const up = new THREE.Vector3(0, 1, 0);
    pose.bones.forEach(([a, b], i) => {
      const pa = pose.joints[a] && pose.joints[a].p, pb = pose.joints[b] && pose.joints[b].p;
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
      if (!s.p) return;
      sensors[i].position.copy(toView(s.p));
      if (s.R && s.R.length === 9) {
        // Sensor axes in tracker coordinates, mapped to view axes the same way as positions.
        const R = s.R;
        const col = (k) => toView([R[k], R[3 + k], R[6 + k]]);
        const m = new THREE.Matrix4().makeBasis(col(0), col(1), col(2));
        sensors[i].quaternion.setFromRotationMatrix(m);
      }
    });
  }

  _draw2d() {
    const ctx = this.canvas.getContext('2d');
    const w = this.canvas.width, h = this.canvas.height;
    ctx.fillStyle = '#10141a';
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
    ctx.strokeStyle = '#3fa9f5'; ctx.lineWidth = 4;
    this.pose.bones.forEach(([a, b]) => {
      const pa = this.pose.joints[a] && this.pose.joints[a].p, pb = this.pose.joints[b] && this.pose.joints[b].p;
      if (!pa || !pb) return;
      const [x1, y1] = project(pa), [x2, y2] = project(pb);
      ctx.beginPath(); ctx.moveTo(x1, y1); ctx.lineTo(x2, y2); ctx.stroke();
    });
    ctx.fillStyle = '#ffc857';
    this.pose.joints.forEach((j) => { if (!j.p) return; const [x, y] = project(j.p); ctx.beginPath(); ctx.arc(x, y, 5, 0, 7); ctx.fill(); });
    ctx.fillStyle = '#e4572e';
    this.pose.sensors.forEach((s) => { if (!s.p) return; const [x, y] = project(s.p); ctx.fillRect(x - 4, y - 4, 8, 8); });
  }
}
