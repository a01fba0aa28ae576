// The calibrated skeleton as the service exports it: the glTF rig of GET /api/sessions/{id}/gltf
// (rest=sensor, animation=false), parsed by three.js's own GLTFLoader and posed from the live `pose`
// message's `rig` (each node's rotation, the root's translation), so the page draws the very file an
// engine would load, moved by the very stream it would read (docs/outputs.md, docs/dashboard.md).

import * as THREE from './vendor/three/three.module.js';
import { GLTFLoader } from './vendor/three/GLTFLoader.js';

// The live rig's frame is Y-up from the Flock's +Z-down world (server/pose.py RIG_UP): rig (x, y, z) =
// tracker (x, −z, y). common.js draws in view = tracker (y, −z, −x) = rig (z, y, −x): a quarter turn about +Y.
export const RIG_UP = '-z';
const RIG_TO_VIEW_Y = Math.PI / 2;

// The rig only, without the take's animation (not needed to drive it): 193 kB for 16 bodies, whatever
// the session's length.
export function rigPath(session) {
  return `/api/sessions/${encodeURIComponent(session)}/gltf?rest=sensor&animation=false`;
}

// A loaded rig: its three.js objects by glTF node name, and the fit it was built from.
export class LoadedRig {
  // session, fitSeq: whose fit the file holds (fitSeq null: the stopped session's stored fit), as the
  // response's X-Flockcal-Fit-Seq header said; markers: {geometry, endGeometry} for the joint-state spheres.
  constructor(gltf, session, fitSeq, { colour, markers }) {
    this.session = session;
    this.fitSeq = fitSeq;
    this.holder = new THREE.Group();
    this.holder.rotation.y = RIG_TO_VIEW_Y;
    this.holder.add(gltf.scene);
    this.scene = gltf.scene;
    this.nodes = {};     // glTF node name (as the file and the pose's rig.rotations spell it) → Object3D
    this.sensorOf = {};  // glTF node name → {sensor, end}: a node is named by its humanoid bone on a human tree
    this.markers = [];   // [{mesh, sensor, kind}]: state-coloured spheres riding on the rig's joints
    this.root = null;
    const json = gltf.parser.json;
    gltf.scene.traverse((o) => {
      // The root moves far from the bind pose: bounds computed there must not cull the figure.
      if (o.isMesh) {
        o.frustumCulled = false;
        if (o.material && o.material.color) o.material.color.setHex(colour);
      }
      const ref = gltf.parser.associations.get(o);
      if (!ref || ref.nodes === undefined) return;
      const def = json.nodes[ref.nodes];
      if (def.mesh !== undefined) return;
      this.nodes[def.name] = o;
      const info = (def.extras && def.extras.flockcal) || {};
      this.sensorOf[def.name] = { sensor: info.sensor, end: !!info.end_site };
      if (info.joint === 'root') this.root = o;
      this.bodyCount = (this.bodyCount || 0) + (info.end_site ? 0 : 1);
      const kind = info.end_site ? 'end' : info.joint;
      const mesh = new THREE.Mesh(info.end_site ? markers.endGeometry : markers.geometry);
      o.add(mesh);
      this.markers.push({ mesh, sensor: info.sensor, kind });
    });
  }

  // Whether this rig is the tree the pose's rotations are for (same bodies, same names, same frame).
  fits(rig) {
    if (!rig || rig.up !== RIG_UP || rig.rest !== 'sensor' || rig.session !== this.session || !this.root) return false;
    const names = Object.keys(rig.rotations || {});
    return names.length === this.bodyCount && names.every((n) => this.nodes[n]);
  }

  // Pose the rig from the message's `rig`: no maths, the numbers go straight into the nodes.
  apply(rig, stateOf) {
    for (const [name, q] of Object.entries(rig.rotations)) this.nodes[name].quaternion.set(q[0], q[1], q[2], q[3]);
    this.root.position.set(rig.root[0], rig.root[1], rig.root[2]);
    for (const m of this.markers) m.mesh.material = stateOf(m.kind, m.sensor);
  }

  // {node name: [x, y, z]}: every node's origin as three.js places it, in the rig's own frame (metres,
  // Y-up, as the file's scene), from the nodes' world matrices.
  jointPositions() {
    this.holder.updateWorldMatrix(true, true);
    const toRig = this.scene.matrixWorld.clone().invert();
    const m = new THREE.Matrix4();
    const p = new THREE.Vector3();
    const out = {};
    for (const [name, o] of Object.entries(this.nodes)) {
      p.setFromMatrixPosition(m.multiplyMatrices(toRig, o.matrixWorld));
      out[name] = [p.x, p.y, p.z];
    }
    return out;
  }

  dispose() {
    this.holder.removeFromParent();
    this.scene.traverse((o) => {
      if (o.isSkinnedMesh && o.skeleton) o.skeleton.dispose();
      if (o.isMesh && !this.markers.some((m) => m.mesh === o)) {
        o.geometry.dispose();
        if (o.material && o.material.dispose) o.material.dispose();
      }
    });
  }
}

export async function parseRig(buffer, session, fitSeq, options) {
  const gltf = await new GLTFLoader().parseAsync(buffer, '');
  return new LoadedRig(gltf, session, fitSeq, options);
}
