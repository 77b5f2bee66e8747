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

const MOUTH = new Set(ARKIT_NAMES.map((n, i) => (/^(jaw|mouth|tongue)/.test(n) ? i : -1)).filter((i) => i >= 0));

// How the meshes' morph targets follow a stream whose weights are named `names`.
// meshes: [{name, targets: [morph target names]}]. Returns {meshes: [{arkit: [[target, stream
// index]...], visemes: [[target, viseme index]...]}], channels, missing, visemes, visemeTerms}
// where visemeTerms[v] = [[stream index, coefficient]...].
export function bindAvatar(meshes, names) {
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
  const useVisemes = ![...found].some((a) => MOUTH.has(a));
  if (!useVisemes) for (const m of perMesh) m.visemes = [];
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
  };
}
