// ARKit weights from the bundled head's motion, in the page: the numbers of
// talkmesh.face.arkit.WeightFitter (least squares on the head's 52 morph targets, clipped to
// [0, 1], then projected gradient steps), the basis read from head.glb's morph targets.

import { ARKIT_NAMES } from "../client/arkit_names.js";

const ITERATIONS = 200;

// Inverse of a symmetric positive definite (k, k) matrix (Gauss-Jordan; k = 52).
function inverse(a, k) {
  const m = new Float64Array(k * 2 * k);
  for (let i = 0; i < k; i++) {
    for (let j = 0; j < k; j++) m[i * 2 * k + j] = a[i * k + j];
    m[i * 2 * k + k + i] = 1;
  }
  for (let c = 0; c < k; c++) {
    let p = c;
    for (let r = c + 1; r < k; r++) if (Math.abs(m[r * 2 * k + c]) > Math.abs(m[p * 2 * k + c])) p = r;
    for (let j = 0; j < 2 * k; j++) [m[c * 2 * k + j], m[p * 2 * k + j]] = [m[p * 2 * k + j], m[c * 2 * k + j]];
    const d = m[c * 2 * k + c];
    for (let j = 0; j < 2 * k; j++) m[c * 2 * k + j] /= d;
    for (let r = 0; r < k; r++) {
      if (r === c) continue;
      const f = m[r * 2 * k + c];
      if (f !== 0) for (let j = 0; j < 2 * k; j++) m[r * 2 * k + j] -= f * m[c * 2 * k + j];
    }
  }
  const out = new Float64Array(k * k);
  for (let i = 0; i < k; i++) for (let j = 0; j < k; j++) out[i * k + j] = m[i * 2 * k + k + j];
  return out;
}

// Largest eigenvalue of a symmetric (k, k) matrix by power iteration.
function largestEigenvalue(a, k) {
  let v = new Float64Array(k).fill(1 / Math.sqrt(k));
  let value = 0;
  for (let it = 0; it < 500; it++) {
    const w = new Float64Array(k);
    for (let i = 0; i < k; i++) for (let j = 0; j < k; j++) w[i] += a[i * k + j] * v[j];
    const norm = Math.hypot(...w);
    if (Math.abs(norm - value) <= 1e-12 * norm) return norm;
    value = norm;
    v = w.map((x) => x / norm);
  }
  return value;
}

export class WeightFitter {
  // mesh: the head (three.js) whose morph targets (relative offsets) carry the ARKit names.
  constructor(mesh) {
    const targets = mesh.geometry.morphAttributes.position;
    const dict = mesh.morphTargetDictionary;
    this.k = ARKIT_NAMES.length;
    this.n = targets[0].array.length;
    this.basis = ARKIT_NAMES.map((name) => {
      if (dict[name] === undefined) throw new Error(`the head lacks the ARKit morph target ${name}`);
      return Float64Array.from(targets[dict[name]].array);
    });
    const k = this.k;
    this.gram = new Float64Array(k * k);
    for (let i = 0; i < k; i++) {
      for (let j = i; j < k; j++) {
        let s = 0;
        const a = this.basis[i];
        const b = this.basis[j];
        for (let x = 0; x < this.n; x++) s += a[x] * b[x];
        this.gram[i * k + j] = this.gram[j * k + i] = s;
      }
    }
    let trace = 0;
    for (let i = 0; i < k; i++) trace += this.gram[i * k + i];
    const reg = Float64Array.from(this.gram);
    for (let i = 0; i < k; i++) reg[i * k + i] += (1e-9 * trace) / k;
    this.inverse = inverse(reg, k);
    this.step = 1 / largestEigenvalue(this.gram, k);
  }

  // One frame's offsets (V * 3) -> Float32Array(52) weights in ARKIT_NAMES order.
  fit(offsets) {
    const { k, n, gram } = this;
    const proj = new Float64Array(k);
    for (let i = 0; i < k; i++) {
      const b = this.basis[i];
      let s = 0;
      for (let x = 0; x < n; x++) s += b[x] * offsets[x];
      proj[i] = s;
    }
    let w = new Float64Array(k);
    for (let i = 0; i < k; i++) {
      let s = 0;
      for (let j = 0; j < k; j++) s += this.inverse[i * k + j] * proj[j];
      w[i] = Math.min(1, Math.max(0, s));
    }
    let next = new Float64Array(k);
    for (let it = 0; it < ITERATIONS; it++) {
      for (let i = 0; i < k; i++) {
        let g = -proj[i];
        for (let j = 0; j < k; j++) g += w[j] * gram[j * k + i];
        next[i] = Math.min(1, Math.max(0, w[i] - this.step * g));
      }
      [w, next] = [next, w];
    }
    return Float32Array.from(w);
  }
}
