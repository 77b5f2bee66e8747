// A VRM whose mouth has no ARKit-named or viseme morph targets (a VRoid model): its expression
// presets (aa, ih, ou, ee, oh, blink) driven through @pixiv/three-vrm from the ARKit weights,
// the visemes made as the viewer makes them for viseme avatars (VISEME_FROM_ARKIT).

import { VRMLoaderPlugin } from "@pixiv/three-vrm";
import { GLTFLoader } from "three/examples/jsm/loaders/GLTFLoader.js";
import { ARKIT_NAMES, VISEME_FROM_ARKIT } from "../viewer/arkit_names.js";

const PRESETS = { aa: "aa", ih: "I", ou: "U", ee: "E", oh: "O" }; // preset -> viseme
const BLINK = ["eyeBlinkLeft", "eyeBlinkRight"].map((n) => ARKIT_NAMES.indexOf(n));

// A .glb/.vrm ArrayBuffer -> gltf, with gltf.userData.vrm where it is a VRM three-vrm reads (a
// VRM it cannot read, e.g. one without the required bones, loads as plain glTF).
export async function parseAvatar(buffer) {
  const loader = new GLTFLoader();
  loader.register((parser) => new VRMLoaderPlugin(parser));
  try {
    return await loader.parseAsync(buffer, "");
  } catch {
    return new GLTFLoader().parseAsync(buffer, "");
  }
}

export class VrmPresets {
  // null when `gltf` is no VRM or has no mouth preset
  static of(gltf) {
    const manager = gltf.userData.vrm && gltf.userData.vrm.expressionManager;
    if (!manager || !Object.keys(PRESETS).some((p) => manager.getExpression(p))) return null;
    return new VrmPresets(gltf.userData.vrm);
  }

  constructor(vrm) {
    this.vrm = vrm;
    this.manager = vrm.expressionManager;
    this.terms = Object.entries(PRESETS).map(([preset, viseme]) => [
      preset,
      Object.entries(VISEME_FROM_ARKIT[viseme] || {}).map(([n, c]) => [ARKIT_NAMES.indexOf(n), c]),
    ]);
    this.names = Object.keys(PRESETS).filter((p) => this.manager.getExpression(p));
    // the morph target the aa preset binds (for tests: the mouth's opening)
    const aa = this.manager.getExpression("aa");
    const bind = aa && (aa._binds || []).find((b) => b.primitives && b.index !== undefined);
    this.mouth = bind ? { mesh: bind.primitives[0], index: bind.index } : null;
  }

  apply(weights) {
    for (const [preset, terms] of this.terms) {
      let x = 0;
      for (const [i, c] of terms) x += c * weights[i];
      this.manager.setValue(preset, Math.min(1, Math.max(0, x)));
    }
    this.manager.setValue("blink", Math.min(1, (weights[BLINK[0]] + weights[BLINK[1]]) / 2));
    this.manager.update();
  }

  opening() {
    if (!this.mouth) return {};
    const { mesh, index } = this.mouth;
    return { [mesh.userData.talkmeshName || mesh.name]: mesh.morphTargetInfluences[index] };
  }
}
