// ARKit blendshapes and Oculus visemes among an avatar's morph target names: the same rules as
// talkmesh.face.arkit_names (tests/test_avatar.py checks that both give the same answers).

export const ARKIT_NAMES = [
  "eyeBlinkLeft", "eyeLookDownLeft", "eyeLookInLeft", "eyeLookOutLeft", "eyeLookUpLeft",
  "eyeSquintLeft", "eyeWideLeft",
  "eyeBlinkRight", "eyeLookDownRight", "eyeLookInRight", "eyeLookOutRight", "eyeLookUpRight",
  "eyeSquintRight", "eyeWideRight",
  "jawForward", "jawLeft", "jawRight", "jawOpen",
  "mouthClose", "mouthFunnel", "mouthPucker", "mouthLeft", "mouthRight",
  "mouthSmileLeft", "mouthSmileRight", "mouthFrownLeft", "mouthFrownRight",
  "mouthDimpleLeft", "mouthDimpleRight", "mouthStretchLeft", "mouthStretchRight",
  "mouthRollLower", "mouthRollUpper", "mouthShrugLower", "mouthShrugUpper",
  "mouthPressLeft", "mouthPressRight", "mouthLowerDownLeft", "mouthLowerDownRight",
  "mouthUpperUpLeft", "mouthUpperUpRight",
  "browDownLeft", "browDownRight", "browInnerUp", "browOuterUpLeft", "browOuterUpRight",
  "cheekPuff", "cheekSquintLeft", "cheekSquintRight",
  "noseSneerLeft", "noseSneerRight",
  "tongueOut",
];

export const VISEMES = ["sil", "PP", "FF", "TH", "DD", "kk", "CH", "SS", "nn", "RR", "aa", "E", "I", "O", "U"];

// viseme -> {ARKit name: coefficient}; weight = clamp(sum(coefficient * ARKit weight), 0, 1).
export const VISEME_FROM_ARKIT = {
  PP: { mouthClose: 1.0, mouthPressLeft: 0.5, mouthPressRight: 0.5 },
  FF: { mouthRollLower: 1.0 },
  TH: { tongueOut: 1.0 },
  aa: { jawOpen: 1.0 },
  E: { mouthStretchLeft: 0.5, mouthStretchRight: 0.5 },
  I: { mouthSmileLeft: 0.5, mouthSmileRight: 0.5 },
  O: { mouthFunnel: 1.0 },
  U: { mouthPucker: 1.0 },
};

const SIDES = { l: "left", r: "right", lt: "left", rt: "right" };
const WORDS = /[A-Z]+(?![a-z])|[A-Z]?[a-z]+|[0-9]+/g;

function lastSegment(name) {
  const parts = String(name).trim().split(/[.|:/\\]/);
  return parts[parts.length - 1];
}

function key(name) {
  const words = (lastSegment(name).match(WORDS) || []).map((w) => w.toLowerCase());
  if (words.length && SIDES[words[words.length - 1]]) words[words.length - 1] = SIDES[words[words.length - 1]];
  return words.join("");
}

const ARKIT_KEYS = new Map(ARKIT_NAMES.map((n, i) => [key(n), i]));
const ARKIT_BY_LENGTH = [...ARKIT_KEYS.keys()].sort((a, b) => b.length - a.length);
const VISEME_KEYS = new Map(VISEMES.map((v, i) => [v.toLowerCase(), i]));

// Index into ARKIT_NAMES of a morph target name as exporters write it; -1 if none.
export function arkitChannel(name) {
  const k = key(name);
  if (ARKIT_KEYS.has(k)) return ARKIT_KEYS.get(k);
  for (const a of ARKIT_BY_LENGTH) if (k.endsWith(a)) return ARKIT_KEYS.get(a);
  return -1;
}

// Index into VISEMES of an Oculus viseme target name (viseme_aa, V_PP); -1 if none.
export function visemeChannel(name) {
  const m = /^(?:viseme|v)[ _-]?([a-z]+)$/i.exec(lastSegment(name));
  if (!m) return -1;
  return VISEME_KEYS.get(m[1].toLowerCase()) ?? -1;
}

// VRM expression presets (1.0 names; VRM 0.x's presetName in VRM0_PRESETS), driven from the
// stream as talkmesh.output.vrm drives them: the mouth presets are the Oculus vowels aa I U E O.
export const VRM_PRESETS = [
  "aa", "ih", "ou", "ee", "oh", "blink", "blinkLeft", "blinkRight",
  "lookUp", "lookDown", "lookLeft", "lookRight",
];
const VRM_MOUTH = VRM_PRESETS.slice(0, 5);
const VRM0_PRESETS = {
  a: "aa", i: "ih", u: "ou", e: "ee", o: "oh", blink: "blink", blink_l: "blinkLeft",
  blink_r: "blinkRight", lookup: "lookUp", lookdown: "lookDown", lookleft: "lookLeft",
  lookright: "lookRight",
};
const PRESET_FROM_ARKIT = {
  aa: VISEME_FROM_ARKIT.aa,
  ih: VISEME_FROM_ARKIT.I,
  ou: VISEME_FROM_ARKIT.U,
  ee: VISEME_FROM_ARKIT.E,
  oh: VISEME_FROM_ARKIT.O,
  blinkLeft: { eyeBlinkLeft: 1.0 },
  blinkRight: { eyeBlinkRight: 1.0 },
  lookUp: { eyeLookUpLeft: 0.5, eyeLookUpRight: 0.5 },
  lookDown: { eyeLookDownLeft: 0.5, eyeLookDownRight: 0.5 },
  lookLeft: { eyeLookOutLeft: 0.5, eyeLookInRight: 0.5 },
  lookRight: { eyeLookInLeft: 0.5, eyeLookOutRight: 0.5 },
}; // blink: the smaller of the two eyes' blinks (only without the one-eye presets)

// The presets of a VRM 1.0 or 0.x glTF JSON with their morph target binds: {version, binds:
// {preset: [[glTF mesh index, target, weight 0-1]...]}}; null when it is no VRM.
export function readVrmExpressions(json) {
  const ext = (json && json.extensions) || {};
  const nodes = json.nodes || [];
  const binds = Object.fromEntries(VRM_PRESETS.map((p) => [p, []]));
  if (ext.VRMC_vrm) {
    const preset = (ext.VRMC_vrm.expressions || {}).preset || {};
    for (const p of VRM_PRESETS) {
      for (const b of (preset[p] || {}).morphTargetBinds || []) {
        const mesh = (nodes[b.node] || {}).mesh;
        if (Number.isInteger(mesh)) binds[p].push([mesh, b.index, b.weight ?? 1.0]);
      }
    }
    return { version: "1.0", binds };
  }
  if (ext.VRM) {
    const groups = (ext.VRM.blendShapeMaster || {}).blendShapeGroups || [];
    for (const g of groups) {
      const p = VRM0_PRESETS[String(g.presetName || "").toLowerCase()];
      if (!p) continue;
      for (const b of g.binds || []) binds[p].push([b.mesh, b.index, (b.weight ?? 100) / 100]);
    }
    return { version: "0.x", binds };
  }
  return null;
}

// Preset values in VRM_PRESETS order from the stream's weights (presetTerms from bindAvatar).
export function presetValues(weights, presetTerms, out) {
  VRM_PRESETS.forEach((p, k) => {
    const terms = presetTerms[k];
    let x = 0;
    if (p === "blink" && terms.length === 2) x = Math.min(weights[terms[0][0]], weights[terms[1][0]]);
    else for (const [i, c] of terms) x += c * weights[i];
    out[k] = Math.min(1, Math.max(0, x));
  });
  return out;
}

const MOUTH = new Set(ARKIT_NAMES.map((n, i) => (/^(jaw|mouth|tongue)/.test(n) ? i : -1)).filter((i) => i >= 0));

// How the meshes' morph targets follow a stream whose weights are named `names`.
// meshes: [{name, targets: [morph target names], mesh: glTF mesh index}]; expressions: a VRM's
// (readVrmExpressions) or null. Returns {meshes: [{arkit: [[target, stream index]...], visemes:
// [[target, viseme index]...], presets: [[target, preset index, weight]...]}], channels, missing,
// visemes, visemeTerms, expressions, vrm, presetTerms} where visemeTerms[v] (and presetTerms[p])
// = [[stream index, coefficient]...]. A VRM without ARKit mouth shapes but with mouth presets
// gets its presets, else an avatar without ARKit mouth shapes its visemes (as talkmesh's files).
export function bindAvatar(meshes, names, expressions = null) {
  const stream = new Map(names.map((n, i) => [n, i]));
  const found = new Set();
  const perMesh = meshes.map(({ targets }) => {
    const arkit = [];
    const visemes = [];
    targets.forEach((t, k) => {
      const v = visemeChannel(t);
      const a = v >= 0 ? -1 : arkitChannel(t);
      if (v >= 0 && VISEME_FROM_ARKIT[VISEMES[v]]) visemes.push([k, v]);
      if (a >= 0) {
        found.add(a);
        if (stream.has(ARKIT_NAMES[a])) arkit.push([k, stream.get(ARKIT_NAMES[a])]);
      }
    });
    return { arkit, visemes };
  });
  const noMouth = ![...found].some((a) => MOUTH.has(a));
  const mouthBound = expressions && VRM_MOUTH.some((p) => expressions.binds[p].length);
  const useVrm = noMouth && Boolean(mouthBound);
  const oneEye = useVrm && expressions.binds.blinkLeft.length && expressions.binds.blinkRight.length;
  perMesh.forEach((m, i) => {
    m.presets = [];
    if (!useVrm) return;
    m.visemes = [];
    VRM_PRESETS.forEach((p, k) => {
      for (const [mesh, target, weight] of expressions.binds[p]) {
        const count = meshes[i].targets.length;
        if (mesh === meshes[i].mesh && target >= 0 && target < count) m.presets.push([target, k, weight]);
      }
    });
  });
  if (!noMouth) for (const m of perMesh) m.visemes = [];
  const presetTerms = VRM_PRESETS.map((p) => {
    // one blink preset for both eyes, or one for each: the others stay at 0
    if ((p === "blink" && oneEye) || (p.startsWith("blink") && p !== "blink" && !oneEye)) return [];
    const terms = p === "blink" ? { eyeBlinkLeft: 1.0, eyeBlinkRight: 1.0 } : PRESET_FROM_ARKIT[p];
    return Object.entries(terms)
      .filter(([n]) => stream.has(n))
      .map(([n, c]) => [stream.get(n), c]);
  });
  const drivenPresets = new Set(perMesh.flatMap((m) => m.presets.map(([, k]) => k)));
  const visemeTerms = VISEMES.map((v) =>
    Object.entries(VISEME_FROM_ARKIT[v] || {})
      .filter(([n]) => stream.has(n))
      .map(([n, c]) => [stream.get(n), c]),
  );
  const drivenVisemes = new Set(perMesh.flatMap((m) => m.visemes.map(([, v]) => v)));
  return {
    meshes: perMesh,
    channels: ARKIT_NAMES.filter((_, i) => found.has(i)),
    missing: ARKIT_NAMES.filter((_, i) => !found.has(i)),
    visemes: VISEMES.filter((_, i) => drivenVisemes.has(i)),
    visemeTerms,
    expressions: VRM_PRESETS.filter((_, k) => drivenPresets.has(k)),
    vrm: useVrm ? expressions.version : "",
    presetTerms,
  };
}
