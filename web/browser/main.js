// talkmesh's bundled model running in the page, no server: a speech file or the microphone, the
// exported speech encoder and generation step (`talkmesh export-onnx`) on onnxruntime-web
// (model.js: WebGPU where present, WebAssembly otherwise), the bundled head's vertices set from
// each frame's motion, or a dropped-in avatar (.glb/.vrm) driven through its ARKit morph targets
// with the weights fitted to that motion (fit.js). scripts/browser_page.py puts the page and its
// files in one folder.
//
// For tests, `window.page`: ready, error (one line), backend ("webgpu" or "wasm") and
// backendNote (why not WebGPU), motion and weights of a file's frames, timing, done; mic {running,
// frames: [{t, rms, latency, weights}], busyMs, encoderMs, audioS}; avatar {name, meshes,
// channels}; opening: per frame shown on an avatar, each driven mesh's jaw-open influence.

import * as THREE from "three";
import { GLTFLoader } from "three/examples/jsm/loaders/GLTFLoader.js";
import { AvatarRig } from "../client/avatar.js";
import { addCapture, microphone, openCapture } from "../client/capture.js";
import { WeightFitter } from "./fit.js";
import { SAMPLE_RATE } from "./logmel.js";
import { Model, Streamer, openSessions } from "./model.js";

const CHUNK_SAMPLES = SAMPLE_RATE / 50; // 20 ms from the microphone
const $ = (id) => document.getElementById(id);
const query = new URLSearchParams(location.search);
const page = (window.page = {
  ready: false, error: null, done: false, motion: [], weights: [], timing: {}, backend: null,
  backendNote: null, mic: null, avatar: null, opening: [],
}); // prettier-ignore

const renderer = new THREE.WebGLRenderer({ antialias: true });
renderer.setSize(innerWidth, innerHeight);
document.body.appendChild(renderer.domElement);
const scene = new THREE.Scene();
scene.add(new THREE.HemisphereLight(0xffffff, 0x404040, 2.5));
const camera = new THREE.PerspectiveCamera(30, innerWidth / innerHeight, 0.01, 100);
let model = null;
let head = null; // the bundled head's mesh
let base = null; // its neutral vertices
let fitter = null;
let shown = null; // the scene shown: the head's or an avatar's
let rig = null; // the avatar's, when one was dropped in
let latest = null; // the motion to show next

function say(text) {
  $("status").textContent = text;
}

function fail(e) {
  page.error = String(e.message || e).split("\n")[0];
  say(page.error);
}

function frame(object) {
  const box = new THREE.Box3().setFromObject(object);
  const center = box.getCenter(new THREE.Vector3());
  const size = box.getSize(new THREE.Vector3()).length();
  camera.position.set(center.x, center.y, center.z + 1.6 * size);
  camera.lookAt(center);
}

function showScene(object) {
  if (shown) scene.remove(shown);
  scene.add(object);
  shown = object;
  frame(object);
  renderer.render(scene, camera);
}

// One frame's motion on what is shown: the head's vertices, or the avatar's morph targets.
function show(motion) {
  if (rig) {
    rig.apply(fitter.fit(motion));
    page.opening.push(rig.opening());
    return;
  }
  const pos = head.geometry.attributes.position;
  for (let i = 0; i < motion.length; i++) pos.array[i] = base[i] + motion[i];
  pos.needsUpdate = true;
}

async function setup() {
  const info = await (await fetch("model.json")).json();
  const [sessions, gltf] = await Promise.all([openSessions(query.get("backend") || "webgpu"), new GLTFLoader().loadAsync("head.glb")]);
  model = new Model(info, sessions);
  gltf.scene.traverse((o) => {
    if (o.isMesh) head = o;
  });
  fitter = new WeightFitter(head);
  head.morphTargetInfluences?.fill(0);
  base = head.geometry.attributes.position.array.slice();
  showScene(gltf.scene);
  Object.assign(page, { backend: sessions.backend, backendNote: sessions.note, ready: true });
  $("backend").textContent = sessions.backend === "webgpu" ? "WebGPU" : `WebAssembly (${sessions.note})`;
  $("mic").disabled = false;
  say("load a speech file, or start the microphone");
}

// A file's audio, mixed to mono at 16 kHz by the browser (decodeAudioData resamples to the
// context's rate); a file it cannot decode is one line.
async function decode(context, file) {
  let decoded;
  try {
    decoded = await context.decodeAudioData(await file.arrayBuffer());
  } catch {
    throw new Error(`${file.name}: not audio this browser can decode; choose a speech recording (wav, mp3, ogg, flac)`);
  }
  if (!decoded.length) throw new Error(`${file.name}: the audio is empty`);
  const audio = new Float32Array(decoded.length);
  for (let c = 0; c < decoded.numberOfChannels; c++) {
    const channel = decoded.getChannelData(c);
    for (let i = 0; i < audio.length; i++) audio[i] += channel[i] / decoded.numberOfChannels;
  }
  return { decoded, audio };
}

let fileContext = null; // the last file's, closed when another file or the microphone starts

function stopFile() {
  if (fileContext) fileContext.close();
  fileContext = null;
}

async function playFile(file) {
  stopMic();
  stopFile();
  page.done = false;
  const context = (fileContext = new AudioContext({ sampleRate: SAMPLE_RATE }));
  const { decoded, audio } = await decode(context, file);
  const frames = Math.max(1, Math.round((audio.length / SAMPLE_RATE) * model.info.fps));
  say(`animating ${frames} frames`);
  const t0 = performance.now();
  const feats = await model.clipFeatures(audio, frames);
  const t1 = performance.now();
  page.motion = await model.generate(feats, frames);
  const t2 = performance.now();
  page.weights = page.motion.map((m) => fitter.fit(m));
  page.timing = { speechMs: t1 - t0, stepsMs: t2 - t1, audioS: audio.length / SAMPLE_RATE, frames };
  const player = context.createBufferSource();
  player.buffer = decoded;
  player.connect(context.destination);
  const start = context.currentTime + 0.05;
  player.start(start);
  player.onended = () => { page.done = true; }; // prettier-ignore
  say(`${frames} frames in ${((t2 - t0) / 1000).toFixed(2)} s (${page.backend})`);
  let last = -1;
  renderer.setAnimationLoop(() => {
    const t = Math.floor((context.currentTime - start) * model.info.fps);
    if (t >= 0 && t < page.motion.length && t !== last) {
      show(page.motion[t]);
      last = t;
      renderer.render(scene, camera); // only when the face changed: the CPU is the model's
    }
  });
}

// --- the microphone: captured at 16 kHz (the shared worklet resamples), streamed through the model

let mic = null;

async function startMic() {
  stopMic();
  stopFile();
  const context = new AudioContext({ sampleRate: SAMPLE_RATE, latencyHint: "interactive" });
  let stream;
  try {
    stream = await microphone();
  } catch (e) {
    await context.close();
    throw e;
  }
  await addCapture(context, SAMPLE_RATE, CHUNK_SAMPLES);
  const state = (page.mic = { running: true, frames: [], busyMs: 0, encoderMs: 0, audioS: 0, wallS: 0 });
  const started = performance.now();
  const options = Object.fromEntries(["hop", "context", "lookahead"].filter((k) => query.has(k)).map((k) => [k, Number(query.get(k))]));
  const streamer = new Streamer(model, options, ({ t, motion, rms, latency }) => {
    latest = motion;
    state.frames.push({ t, rms, latency, weights: Array.from(fitter.fit(motion)) });
    Object.assign(state, {
      busyMs: streamer.busyMs,
      encoderMs: streamer.encoderMs,
      audioS: streamer.samples / SAMPLE_RATE,
      wallS: (performance.now() - started) / 1000,
      options: { hop: streamer.hop, context: streamer.context, lookahead: streamer.lookahead },
    });
    if (t % 15 === 0) say(`microphone: frame ${t}, ${latency.toFixed(0)} ms behind the voice (${page.backend})`);
  });
  const capture = openCapture(context, context.createMediaStreamSource(stream), (buffer) => {
    const pcm = new Int16Array(buffer);
    const samples = new Float32Array(pcm.length);
    for (let i = 0; i < pcm.length; i++) samples[i] = pcm[i] / 32768;
    streamer.push(samples);
  });
  mic = { context, stream, capture, streamer };
  $("stop").disabled = false;
  say(`microphone: listening (${page.backend})`);
  renderer.setAnimationLoop(() => {
    if (!latest) return;
    show(latest);
    latest = null;
    renderer.render(scene, camera);
  });
}

function stopMic() {
  if (!mic) return;
  mic.streamer.stop();
  mic.capture.close();
  mic.stream.getTracks().forEach((t) => t.stop());
  mic.context.close();
  page.mic.running = false;
  mic = null;
  $("stop").disabled = true;
  say("microphone stopped");
}

// --- a dropped-in avatar (.glb/.vrm): its ARKit morph targets (or visemes) follow the motion

async function loadAvatar(file) {
  if (!/\.(glb|vrm)$/i.test(file.name)) throw new Error(`${file.name}: choose a .glb or .vrm avatar`);
  let gltf;
  try {
    gltf = await new GLTFLoader().parseAsync(await file.arrayBuffer(), "");
  } catch (e) {
    throw new Error(`${file.name}: not a glTF binary three.js can read (${String(e.message || e).split("\n")[0]})`);
  }
  const candidate = new AvatarRig(gltf);
  const { binding } = candidate;
  if (!candidate.driven.length) {
    throw new Error(`${file.name} has no morph targets with ARKit names, visemes or VRM mouth presets`);
  }
  rig = candidate;
  showScene(gltf.scene);
  page.avatar = {
    name: file.name,
    meshes: candidate.driven.map((m) => m.userData.talkmeshName),
    channels: binding.channels,
    presets: binding.expressions,
  };
  page.opening = [];
  const what = binding.expressions.length ? `VRM ${binding.vrm} presets ${binding.expressions.join(" ")}` : `${binding.channels.length} ARKit channels`;
  say(`${file.name}: ${what} driven`);
}

const guard = (f) => (...args) => f(...args).catch(fail); // prettier-ignore
$("file").addEventListener("change", guard(async (e) => { page.error = null; await playFile(e.target.files[0]); })); // prettier-ignore
$("mic").addEventListener("click", guard(async () => { page.error = null; await startMic(); })); // prettier-ignore
$("stop").addEventListener("click", () => stopMic());
$("avatar").addEventListener("change", guard(async (e) => loadAvatar(e.target.files[0])));
window.addEventListener("dragover", (e) => e.preventDefault());
window.addEventListener("drop", guard(async (e) => {
  e.preventDefault();
  const file = e.dataTransfer && e.dataTransfer.files[0];
  if (file) await loadAvatar(file);
})); // prettier-ignore

setup().catch(fail);
