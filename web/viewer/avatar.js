// Avatars (a loaded .glb/.vrm) driven by ARKit weights, shared by the viewer and the in-browser
// page: every mesh whose morph targets carry ARKit names (in exporters' spellings,
// arkit_names.js) follows the weights; one with Oculus visemes only gets them from the ARKit
// weights.

import { ARKIT_NAMES, bindAvatar } from "./arkit_names.js";

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

// Drive `gltf`'s morph meshes from weights named `names` (ARKIT_NAMES by default).
export class AvatarRig {
  constructor(gltf, names = ARKIT_NAMES) {
    this.meshes = [];
    gltf.scene.traverse((o) => {
      if (o.isMesh && o.morphTargetInfluences && o.morphTargetInfluences.length) {
        o.userData.talkmeshTargets = targetNames(o, gltf.parser);
        o.userData.talkmeshName = (meshDef(o, gltf.parser) || {}).name || o.name || "mesh";
        this.meshes.push(o);
      }
    });
    this.binding = bindAvatar(this.meshes.map((m) => ({ targets: m.userData.talkmeshTargets })), names);
    this.visemeValues = new Float32Array(this.binding.visemeTerms.length);
    this.driven = this.meshes.filter((_, i) => this.binding.meshes[i].arkit.length || this.binding.meshes[i].visemes.length);
  }

  apply(weights) {
    const { visemeTerms, meshes } = this.binding;
    for (let v = 0; v < visemeTerms.length; v++) {
      let x = 0;
      for (const [i, c] of visemeTerms[v]) x += c * weights[i];
      this.visemeValues[v] = Math.min(1, Math.max(0, x));
    }
    this.meshes.forEach((mesh, m) => {
      const influences = mesh.morphTargetInfluences;
      for (const [k, i] of meshes[m].arkit) influences[k] = weights[i];
      for (const [k, v] of meshes[m].visemes) influences[k] = this.visemeValues[v];
    });
  }
}
