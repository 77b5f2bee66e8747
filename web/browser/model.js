// The exported model (`talkmesh export-onnx`: ct.speech.onnx, ct.onnx) on onnxruntime-web: WebGPU
// where the browser has it, WebAssembly otherwise; a whole clip's features, one step at a time
// with the state carried over, and a microphone's stream a hop at a time.

import * as wasmOrt from "onnxruntime-web/wasm";
import { MelStream, SAMPLE_RATE, logMel } from "./logmel.js";

const ENCODER_HOP = 320; // samples per speech feature (50 Hz)
const MEL_HOP = 160; // samples per mel frame
const FEATURE_RATE = SAMPLE_RATE / ENCODER_HOP;
const WINDOW = 3000; // mel frames per encoder window (30 s)
// onnxruntime-web's WebGPU build runs WebAssembly too, but its (asyncify) build took 31-33 ms per
// step where the plain WebAssembly build took 19-24 (headless Chromium, 2 shared cores): it is
// loaded only where WebGPU can run.
let ort = wasmOrt;

function configure(module) {
  module.env.wasm.wasmPaths = "./";
  module.env.wasm.numThreads = 1; // threads need a cross-origin isolated page
  return module;
}

// Why WebGPU cannot run here, or null when it can.
async function webgpuMissing() {
  if (!navigator.gpu) return "no WebGPU in this browser (navigator.gpu is missing)";
  try {
    if (!(await navigator.gpu.requestAdapter())) return "WebGPU has no adapter here";
  } catch (e) {
    return `WebGPU has no adapter here (${e.message || e})`;
  }
  return null;
}

// Both graphs on WebGPU, else on WebAssembly -> {speech, step, backend, note}; note says why
// WebGPU did not run ("" when it did). `prefer` "wasm" skips WebGPU.
export async function openSessions(prefer = "webgpu") {
  let note = prefer === "wasm" ? "WebAssembly asked for" : await webgpuMissing();
  if (!note) {
    try {
      ort = configure(await import("onnxruntime-web/webgpu"));
      const options = { executionProviders: ["webgpu"] };
      const [speech, step] = await Promise.all([
        ort.InferenceSession.create("ct.speech.onnx", options),
        ort.InferenceSession.create("ct.onnx", options),
      ]);
      return { speech, step, backend: "webgpu", note: "" };
    } catch (e) {
      note = `WebGPU failed (${String(e.message || e).split("\n")[0]})`;
    }
  }
  ort = configure(wasmOrt);
  const options = { executionProviders: ["wasm"] };
  const [speech, step] = await Promise.all([
    ort.InferenceSession.create("ct.speech.onnx", options),
    ort.InferenceSession.create("ct.onnx", options),
  ]);
  return { speech, step, backend: "wasm", note };
}

export class Model {
  // info: model.json (fps, n_mels, speech_dim, style, state shapes; face: the VQ decoder's head
  // term, for a model whose step graph takes one)
  constructor(info, { speech, step, backend, note }) {
    Object.assign(this, { speechSession: speech, stepSession: step, backend, note, info });
    this.D = info.speech_dim;
  }

  async encode(mel, width) {
    const input = new ort.Tensor("float32", mel, [1, this.info.n_mels, width]);
    return (await this.speechSession.run({ mel: input })).features.data; // (width / 2, D)
  }

  // A whole clip (Float32Array, 16 kHz) -> (frames, D) features, as OnnxModel.features: the
  // log-mel in 30 s windows, each encoded on its own, linearly interpolated with corners aligned.
  async clipFeatures(audio, frames) {
    const valid = Math.ceil(audio.length / ENCODER_HOP);
    const padded = new Float32Array(valid * ENCODER_HOP);
    padded.set(audio);
    const { n_mels: M } = this.info;
    const { mel, frames: melFrames } = logMel(padded, M);
    const all = new Float32Array(valid * this.D);
    let at = 0;
    for (let start = 0; start < melFrames; start += WINDOW) {
      const width = Math.min(WINDOW, melFrames - start);
      const window = new Float32Array(M * width);
      for (let m = 0; m < M; m++) window.set(mel.subarray(m * melFrames + start, m * melFrames + start + width), m * width);
      const part = await this.encode(window, width);
      all.set(part.subarray(0, Math.min(part.length, all.length - at)), at);
      at += part.length;
    }
    const out = new Float32Array(frames * this.D);
    for (let t = 0; t < frames; t++) {
      const x = frames > 1 ? (t * (valid - 1)) / (frames - 1) : 0;
      this.interpolate(all, valid, x, out, t);
    }
    return out;
  }

  // out[t] = features at the (fractional) 50 Hz position x of feats (N, D), clamped to its ends.
  interpolate(feats, N, x, out, t) {
    const D = this.D;
    x = Math.max(0, Math.min(N - 1, x));
    const i = Math.floor(x);
    const j = Math.min(i + 1, N - 1);
    const w = x - i;
    for (let d = 0; d < D; d++) out[t * D + d] = feats[i * D + d] * (1 - w) + feats[j * D + d] * w;
  }

  // The state before the first frame.
  start() {
    this.style = new ort.Tensor("float32", Float32Array.from(this.info.style), [1, this.info.style.length]);
    const { face } = this.info;
    this.face = face ? new ort.Tensor("float32", Float32Array.from(face), [1, face.length]) : null;
    const state = {};
    for (const [name, shape] of Object.entries(this.info.state)) {
      const data = new Float32Array(shape.reduce((a, b) => a * b, 1));
      if (name === "x_in") data.set(this.info.style);
      state[name] = new ort.Tensor("float32", data, [1, ...shape]);
    }
    return state;
  }

  // Frame t's motion (V * 3 offsets) from its feature (D,) -> [motion, next state].
  async step(feature, t, state) {
    const out = await this.stepSession.run({
      feature: new ort.Tensor("float32", feature, [1, this.D]),
      t: new ort.Tensor("int64", BigInt64Array.from([BigInt(t)]), [1]),
      style: this.style,
      ...(this.face ? { face: this.face } : {}),
      ...state,
    });
    const next = Object.fromEntries(Object.keys(state).map((n) => [n, out[`next_${n}`]]));
    return [out.motion.data, next];
  }

  // Every frame's motion of a clip's features (frames, D).
  async generate(feats, frames) {
    let state = this.start();
    const motion = [];
    for (let t = 0; t < frames; t++) {
      let m;
      [m, state] = await this.step(feats.slice(t * this.D, (t + 1) * this.D), t, state);
      motion.push(m);
    }
    return motion;
  }
}

// A microphone's audio through the model as it arrives. Every `hop` seconds of new audio, the
// speech encoder runs on the last context + hop + lookahead seconds of log-mel (MelStream: each
// mel frame computed once), and the frames whose time is at least `lookahead` before the end of
// the audio step with the state carried over (the encoder attends both ways, so a frame's
// features wait for that much audio after it). onFrame({t, motion, rms, ready, latency}) per
// frame; latency: ms from the arrival of the frame's audio to its motion.
export class Streamer {
  constructor(model, { hop = 1.0, context = 3.0, lookahead = 0.3 } = {}, onFrame = () => {}) {
    Object.assign(this, { model, hop, context, lookahead, onFrame });
    this.fps = model.info.fps;
    this.mel = new MelStream(model.info.n_mels);
    this.samples = 0; // received
    this.arrivals = []; // [end sample, performance.now()] of each chunk
    this.audioTail = new Float32Array(0); // recent samples, for each frame's loudness
    this.tailStart = 0;
    this.next = 0; // the next frame to compute
    this.encodedTo = 0; // samples covered by the last encoder run
    this.state = model.start();
    this.busyMs = 0; // encoder + steps
    this.encoderMs = 0;
    this.running = false;
    this.stopped = false;
  }

  push(samples, at = performance.now()) {
    if (this.stopped) return;
    this.mel.push(samples);
    this.samples += samples.length;
    this.arrivals.push([this.samples, at]);
    const joined = new Float32Array(this.audioTail.length + samples.length);
    joined.set(this.audioTail);
    joined.set(samples, this.audioTail.length);
    const keep = Math.ceil((this.context + this.hop + this.lookahead + 2) * SAMPLE_RATE);
    const drop = Math.max(0, joined.length - keep);
    this.audioTail = joined.slice(drop);
    this.tailStart += drop;
    if (!this.running) this.pump();
  }

  stop() {
    this.stopped = true;
  }

  arrival(sample) {
    while (this.arrivals.length > 1 && this.arrivals[1][0] <= sample) this.arrivals.shift();
    const hit = this.arrivals.find(([end]) => end >= sample);
    return hit ? hit[1] : performance.now();
  }

  rms(t) {
    const a = Math.round((t / this.fps) * SAMPLE_RATE) - this.tailStart;
    const b = a + Math.round(SAMPLE_RATE / this.fps);
    let s = 0;
    let n = 0;
    for (let i = Math.max(0, a); i < Math.min(b, this.audioTail.length); i++, n++) s += this.audioTail[i] ** 2;
    return n ? Math.sqrt(s / n) : 0;
  }

  async pump() {
    this.running = true;
    try {
      while (!this.stopped && this.samples - this.encodedTo >= this.hop * SAMPLE_RATE) await this.advance();
    } finally {
      this.running = false;
    }
  }

  async advance() {
    const t0 = performance.now();
    const end = Math.floor(this.samples / ENCODER_HOP) * ENCODER_HOP; // whole features
    const melEnd = Math.min(this.mel.frames, end / MEL_HOP) & ~1; // even: 2 mel frames per feature
    const span = Math.ceil((this.context + this.hop + this.lookahead) * FEATURE_RATE) * 2;
    const melStart = Math.max(this.mel.logStart + (this.mel.logStart & 1), melEnd - span);
    const width = melEnd - melStart;
    const feats = await this.model.encode(this.mel.window(melStart, melEnd), width);
    const N = width / 2;
    const first = melStart / 2; // the 50 Hz index of feats[0]
    const t1 = performance.now();
    this.encoderMs += t1 - t0;
    this.encodedTo = this.samples;
    const last = Math.floor((melEnd * MEL_HOP / SAMPLE_RATE - this.lookahead) * this.fps); // exclusive
    const feature = new Float32Array(this.model.D);
    while (this.next < last && !this.stopped) {
      const t = this.next++;
      this.model.interpolate(feats, N, (t / this.fps) * FEATURE_RATE - first, feature, 0);
      const t2 = performance.now();
      const [motion, state] = await this.model.step(feature, t, this.state);
      this.state = state;
      const ready = performance.now();
      this.busyMs += ready - t2;
      const heard = this.arrival(Math.ceil(((t + 1) / this.fps) * SAMPLE_RATE));
      this.onFrame({ t, motion, rms: this.rms(t), ready, latency: ready - heard });
    }
    this.busyMs += t1 - t0;
  }
}
