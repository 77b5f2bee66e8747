// Avatars (a loaded .glb/.vrm, or any three.js object with morph targets) driven by ARKit
// weights: the one binding that talkmesh-client, the viewer of `talkmesh serve` and the
// in-browser page use (the rules are arkit_names.js's bindAvatar).

import { ARKIT_NAMES, VRM_PRESETS, bindAvatar, presetValues, readVrmExpressions } from "./arkit_names.js";

// Morph target names of a three.js mesh: its dictionary (from mesh.extras.targetNames), else the
// glTF primitive's extras.targetNames (UniVRM writes them there), which then fill the dictionary.
export function targetNames(mesh, parser) {
  const count = mesh.morphTargetInfluences.length;
  const names = new Array(count).fill("");
  for (const [name, k] of Object.entries(mesh.morphTargetDictionary || {})) names[k] = name;
  if (names.some((n, k) => n !== String(k)) || !parser) return names; // three.js numbers unnamed ones
  const def = meshDef(mesh, parser);
  const where = parser.associations.get(mesh);
  const primitive = def && (def.primitives[where.primitives ?? 0] || def.primitives[0]);
  const stored = primitive && primitive.extras && primitive.extras.targetNames;
  if (!Array.isArray(stored) || stored.length !== count) return names;
  mesh.morphTargetDictionary = Object.fromEntries(stored.map((n, k) => [String(n), k]));
  return stored.map(String);
}

// The glTF mesh a three.js mesh came from (three.js names the object after the node).
export function meshDef(mesh, parser) {
  const where = parser && parser.associations.get(mesh);
  return where && where.meshes !== undefined && parser.json.meshes ? parser.json.meshes[where.meshes] : null;
}

// Drive the morph meshes of `gltf` (a GLTFLoader result {scene, parser}, or a three.js object:
// then names come from its meshes' morphTargetDictionary and no VRM extension is read) from
// weights named `names` (ARKIT_NAMES by default): ARKit-named targets, else a VRM's mouth presets
// through the targets its extension binds, else Oculus visemes.
export class AvatarRig {
  constructor(gltf, names = ARKIT_NAMES) {
    const loaded = Boolean(gltf.scene) && !gltf.isObject3D; // a loader's result, not an object
    const parser = loaded ? gltf.parser || null : null;
    this.scene = loaded ? gltf.scene : gltf;
    this.meshes = [];
    this.scene.traverse((o) => {
      if (o.isMesh && o.morphTargetInfluences && o.morphTargetInfluences.length) {
        o.userData.talkmeshTargets = targetNames(o, parser);
        o.userData.talkmeshName = (meshDef(o, parser) || {}).name || o.name || "mesh";
        const where = parser && parser.associations.get(o);
        o.userData.talkmeshMesh = where ? where.meshes : undefined;
        this.meshes.push(o);
      }
    });
    this.expressions = parser ? readVrmExpressions(parser.json) : null;
    this.bind(names);
  }

  // (Re)bind to a stream whose weights are named `names` (a server's hello may name its own).
  bind(names) {
    const described = this.meshes.map((m) => ({ targets: m.userData.talkmeshTargets, mesh: m.userData.talkmeshMesh }));
    this.binding = bindAvatar(described, names, this.expressions);
    this.visemeValues = new Float32Array(this.binding.visemeTerms.length);
    this.presetValues = new Float32Array(this.binding.presetTerms.length);
    const bound = (b) => b.arkit.length || b.visemes.length || b.presets.length;
    this.driven = this.meshes.filter((_, i) => bound(this.binding.meshes[i]));
    return this.binding;
  }

  // How many morph targets the weights move, over all meshes.
  targetCount() {
    const count = (m) => m.arkit.length + m.visemes.length + new Set(m.presets.map(([k]) => k)).size;
    return this.binding.meshes.reduce((n, m) => n + count(m), 0);
  }

  apply(weights) {
    const { visemeTerms, presetTerms, meshes } = this.binding;
    for (let v = 0; v < visemeTerms.length; v++) {
      let x = 0;
      for (const [i, c] of visemeTerms[v]) x += c * weights[i];
      this.visemeValues[v] = Math.min(1, Math.max(0, x));
    }
    if (presetTerms.length) presetValues(weights, presetTerms, this.presetValues);
    this.meshes.forEach((mesh, m) => {
      const influences = mesh.morphTargetInfluences;
      const { arkit, visemes, presets } = meshes[m];
      for (const [k, i] of arkit) influences[k] = weights[i];
      for (const [k, v] of visemes) influences[k] = this.visemeValues[v];
      // a target several presets bind: the sum of preset x bind weight, clipped to [0, 1]
      for (const [k] of presets) influences[k] = 0;
      for (const [k, p, w] of presets) influences[k] += this.presetValues[p] * w;
      for (const [k] of presets) influences[k] = Math.min(1, Math.max(0, influences[k]));
    });
  }

  // Each driven mesh's mouth opening: its jaw-open (or viseme aa) target, else the target its aa
  // preset binds.
  opening() {
    const out = {};
    this.meshes.forEach((mesh, m) => {
      const d = mesh.morphTargetDictionary || {};
      const name = Object.keys(d).find((n) => /jaw.?open|viseme_aa/i.test(n));
      const aa = this.binding.meshes[m].presets.find(([, p]) => VRM_PRESETS[p] === "aa");
      const k = name !== undefined ? d[name] : aa ? aa[0] : undefined;
      if (k !== undefined && this.driven.includes(mesh)) out[mesh.userData.talkmeshName] = mesh.morphTargetInfluences[k];
    });
    return out;
  }
}
