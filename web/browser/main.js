// talkmesh's bundled model running in the page, no server: the speech file's log-mel
// (logmel.js), the exported speech encoder and generation step (`talkmesh export-onnx`) on
// onnxruntime-web (WebAssembly), the head's vertices set from each frame's motion, played in step
// with the audio. scripts/browser_page.py puts the page and its files in one folder.

import * as ort from "onnxruntime-web/wasm";
import * as THREE from "three";
import { GLTFLoader } from "three/examples/jsm/loaders/GLTFLoader.js";
import { SAMPLE_RATE, logMel } from "./logmel.js";

const ENCODER_HOP = 320; // samples per speech feature (50 Hz)
const WINDOW = 3000; // mel frames per encoder window (30 s)
ort.env.wasm.wasmPaths = "./";
ort.env.wasm.numThreads = 1; // threads need a cross-origin isolated page

const status = document.getElementById("status");
const page = (window.page = { ready: false, error: null, done: false, motion: [], timing: {} });

const renderer = new THREE.WebGLRenderer({ antialias: true });
renderer.setSize(innerWidth, innerHeight);
document.body.appendChild(renderer.domElement);
const scene = new THREE.Scene();
scene.add(new THREE.HemisphereLight(0xffffff, 0x404040, 2.5));
const camera = new THREE.PerspectiveCamera(30, innerWidth / innerHeight, 0.01, 10);
camera.position.set(0, 0, 0.6);
let head = null;
let base = null;

async function setup() {
  const info = await (await fetch("model.json")).json();
  const [speech, step, gltf] = await Promise.all([
    ort.InferenceSession.create("ct.speech.onnx"),
    ort.InferenceSession.create("ct.onnx"),
    new GLTFLoader().loadAsync("head.glb"),
  ]);
  scene.add(gltf.scene);
  gltf.scene.traverse((o) => { if (o.isMesh) head = o; });
  head.morphTargetInfluences?.fill(0);
  base = head.geometry.attributes.position.array.slice();
  camera.lookAt(new THREE.Box3().setFromObject(gltf.scene).getCenter(new THREE.Vector3()));
  Object.assign(page, { info, speech, step, ready: true });
  status.textContent = "load a speech file";
}

// Whisper features (N, D) at 50 Hz -> (frames, D) by linear interpolation, corners aligned.
function toFrames(feats, N, D, frames) {
  const out = new Float32Array(frames * D);
  for (let t = 0; t < frames; t++) {
    const x = frames > 1 ? (t * (N - 1)) / (frames - 1) : 0;
    const i = Math.min(Math.floor(x), N - 1);
    const j = Math.min(i + 1, N - 1);
    const w = x - i;
    for (let d = 0; d < D; d++) out[t * D + d] = feats[i * D + d] * (1 - w) + feats[j * D + d] * w;
  }
  return out;
}

async function features(audio, frames) {
  const valid = Math.ceil(audio.length / ENCODER_HOP);
  const padded = new Float32Array(valid * ENCODER_HOP);
  padded.set(audio);
  const { mel, frames: melFrames } = logMel(padded, page.info.n_mels);
  const parts = [];
  for (let start = 0; start < melFrames; start += WINDOW) {
    const width = Math.min(WINDOW, melFrames - start);
    const window = new Float32Array(page.info.n_mels * width);
    for (let m = 0; m < page.info.n_mels; m++) {
      window.set(mel.subarray(m * melFrames + start, m * melFrames + start + width), m * width);
    }
    const out = await page.speech.run({ mel: new ort.Tensor("float32", window, [1, page.info.n_mels, width]) });
    parts.push(out.features.data);
  }
  const D = page.info.speech_dim;
  const all = new Float32Array(parts.reduce((n, p) => n + p.length, 0));
  let at = 0;
  for (const p of parts) { all.set(p, at); at += p.length; }
  return toFrames(all.subarray(0, valid * D), valid, D, frames);
}

// Every frame's motion (V * 3 offsets), one step at a time, the state carried over.
async function generate(feats, frames) {
  const D = page.info.speech_dim;
  const style = new ort.Tensor("float32", Float32Array.from(page.info.style), [1, page.info.style.length]);
  let state = {};
  for (const [name, shape] of Object.entries(page.info.state)) {
    const data = new Float32Array(shape.reduce((a, b) => a * b, 1));
    if (name === "x_in") data.set(page.info.style);
    state[name] = new ort.Tensor("float32", data, [1, ...shape]);
  }
  const motion = [];
  for (let t = 0; t < frames; t++) {
    const out = await page.step.run({
      feature: new ort.Tensor("float32", feats.slice(t * D, (t + 1) * D), [1, D]),
      t: new ort.Tensor("int64", BigInt64Array.from([BigInt(t)]), [1]),
      style,
      ...state,
    });
    motion.push(out.motion.data);
    state = Object.fromEntries(Object.keys(state).map((n) => [n, out[`next_${n}`]]));
  }
  return motion;
}

async function play(file) {
  // a 16 kHz context: decodeAudioData resamples the file straight to the model's rate (a 16 kHz
  // file's samples come through as they are), and plays it
  const context = new AudioContext({ sampleRate: SAMPLE_RATE });
  const decoded = await context.decodeAudioData(await file.arrayBuffer());
  const audio = new Float32Array(decoded.length);
  for (let c = 0; c < decoded.numberOfChannels; c++) {
    const channel = decoded.getChannelData(c);
    for (let i = 0; i < audio.length; i++) audio[i] += channel[i] / decoded.numberOfChannels;
  }
  const frames = Math.max(1, Math.round((audio.length / SAMPLE_RATE) * page.info.fps));
  status.textContent = `animating ${frames} frames`;
  const t0 = performance.now();
  const feats = await features(audio, frames);
  const t1 = performance.now();
  page.motion = await generate(feats, frames);
  const t2 = performance.now();
  page.timing = { speechMs: t1 - t0, stepsMs: t2 - t1, audioS: audio.length / SAMPLE_RATE, frames };
  const player = context.createBufferSource();
  player.buffer = decoded;
  player.connect(context.destination);
  const start = context.currentTime + 0.05;
  player.start(start);
  page.done = true;
  status.textContent = `${frames} frames in ${((t2 - t0) / 1000).toFixed(2)} s`;
  renderer.setAnimationLoop(() => {
    const t = Math.floor((context.currentTime - start) * page.info.fps);
    if (t >= 0 && t < page.motion.length) {
      const pos = head.geometry.attributes.position;
      const m = page.motion[t];
      for (let i = 0; i < m.length; i++) pos.array[i] = base[i] + m[i];
      pos.needsUpdate = true;
    }
    renderer.render(scene, camera);
  });
}

document.getElementById("file").addEventListener("change", (event) => {
  play(event.target.files[0]).catch((e) => {
    page.error = String(e.message || e);
    status.textContent = page.error;
  });
});

setup().catch((e) => {
  page.error = String(e.message || e);
  status.textContent = page.error;
});
renderer.setAnimationLoop(() => renderer.render(scene, camera));
