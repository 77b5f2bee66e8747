// The browser viewer of `talkmesh serve`.
//
// Streams microphone or audio-file sound to /ws/stream as 16 kHz mono int16 PCM in 20 ms chunks and
// drives the ARKit morph targets of /head.glb with the weights the server sends back, one binary
// "TMF1" message per frame. Bundled by esbuild (`npm run build:viewer`): no CDN.
//
// An avatar (`talkmesh serve --avatar FILE`, or a .glb/.vrm dropped on the page) replaces the
// head, bound by talkmesh-client's AvatarRig (web/client/avatar.js): every mesh whose morph targets
// carry ARKit names (in exporters' spellings, see web/client/arkit_names.js) follows the stream;
// one with Oculus visemes only gets them from the ARKit weights, and a VRM without ARKit mouth
// shapes its expression presets (aa ih ou ee oh, blinks, looks) through the morph targets the VRM
// extension binds to them, as `animate --avatar` files do.
//
// For tests, `window.talkmesh` is the live state: state, framesReceived, latencyMs {median, p95},
// fps, weightHistory {jawOpen}, lastWeights, plus names, streamFps, lookaheadMs, model, endFrames,
// error, avatar {name, meshes, channels, missing, visemes, expressions, vrm} and head (the three.js
// scene).

import * as THREE from "three";
import { OrbitControls } from "three/addons/controls/OrbitControls.js";
import { RoomEnvironment } from "three/addons/environments/RoomEnvironment.js";
import { GLTFLoader } from "three/addons/loaders/GLTFLoader.js";
import { ARKIT_NAMES } from "../client/arkit_names.js";
import { AvatarRig } from "../client/avatar.js";
import { addCapture } from "../client/capture.js";
import { parseFrame } from "../client/index.js";

const SAMPLE_RATE = 16000; // what the server expects
const CHUNK_MS = 20;
const CHUNK_SAMPLES = (SAMPLE_RATE * CHUNK_MS) / 1000;
const HISTORY_FRAMES = 300;
const LATENCY_WINDOW_MS = 2000;
const STATS_EVERY_MS = 250;

const talkmesh = {
  state: "loading",
  framesReceived: 0,
  latencyMs: { median: null, p95: null },
  fps: 0,
  weightHistory: { jawOpen: [] },
  lastWeights: null,
  headPose: null, // the last frame's [pitch, yaw, roll (radians), x, y, z (metres)], if any
  names: null,
  streamFps: null,
  lookaheadMs: null,
  model: null,
  endFrames: null,
  error: null,
  avatar: null,
  loading: null, // while a model downloads: { label, loaded, total } in bytes (total 0: unknown)
  loadSteps: 0, // progress events seen while downloading (tests check the page showed progress)
};
// The three.js head (for tests that read morphTargetInfluences); not enumerable, so that
// serialising `window.talkmesh` (e.g. Playwright's page.evaluate) does not walk the scene graph.
Object.defineProperty(talkmesh, "head", { value: null, writable: true, enumerable: false });
window.talkmesh = talkmesh;

const $ = (id) => document.getElementById(id);

let audioContext = null;

async function audio() {
  if (!audioContext) {
    audioContext = new AudioContext({ latencyHint: "interactive" });
    await addCapture(audioContext, SAMPLE_RATE, CHUNK_SAMPLES);
  }
  if (audioContext.state === "suspended") await audioContext.resume();
  return audioContext;
}

// --- the scene

const container = $("view");
const renderer = new THREE.WebGLRenderer({ antialias: true });
renderer.setPixelRatio(Math.min(window.devicePixelRatio, 2));
renderer.toneMapping = THREE.NeutralToneMapping;
container.appendChild(renderer.domElement);

const scene = new THREE.Scene();
scene.background = new THREE.Color(0x3a3d42);
// Soft image-based light from a neutral room, plus a key light from above right for shape.
const pmrem = new THREE.PMREMGenerator(renderer);
scene.environment = pmrem.fromScene(new RoomEnvironment(), 0.04).texture;
scene.environmentIntensity = 0.45;
const key = new THREE.DirectionalLight(0xfff4e8, 1.4);
key.position.set(0.8, 1.0, 1.2);
scene.add(key);

const camera = new THREE.PerspectiveCamera(28, 1, 0.01, 100);
camera.position.set(0, 0, 1);
const controls = new OrbitControls(camera, renderer.domElement);
controls.enableDamping = true;

function resize() {
  const w = container.clientWidth || 1;
  const h = container.clientHeight || 1;
  renderer.setSize(w, h, false);
  camera.aspect = w / h;
  // Centre the head in the room the panel leaves on its right, where the window is wide enough.
  const panel = $("panel").getBoundingClientRect().right;
  const shift = w > 2.2 * panel ? panel / 2 : 0;
  if (shift) camera.setViewOffset(w, h, -shift, 0, w, h);
  else camera.clearViewOffset();
  camera.updateProjectionMatrix();
}
window.addEventListener("resize", resize);
resize();

let rig = null; // the shown model's AvatarRig: its morph meshes bound to the stream's names

function frameHead(object) {
  const box = new THREE.Box3().setFromObject(object);
  const center = box.getCenter(new THREE.Vector3());
  const size = box.getSize(new THREE.Vector3());
  const fit = Math.max(size.y, size.x / camera.aspect) / (2 * Math.tan(THREE.MathUtils.degToRad(camera.fov / 2)));
  camera.position.set(center.x, center.y + 0.05 * size.y, center.z + size.z / 2 + 1.05 * fit);
  camera.near = fit / 50;
  camera.far = fit * 50;
  camera.updateProjectionMatrix();
  controls.target.copy(center);
  controls.update();
}

// The head pose of a frame: a vertex v goes to R v + t, R = Ry(yaw) Rx(pitch) Rz(roll), which is
// three.js's Euler order "YXZ". The bundled head.glb moves as a whole (its frame is the pose's);
// an avatar turns its head bone (a VRM's humanoid head, else a bone named "head", e.g.
// J_Bip_C_Head) about its joint,
// by the pose's rotation in the world frame; an avatar without one keeps its head still.
let poseTarget = null;
const poseEuler = new THREE.Euler();
const poseTurn = new THREE.Quaternion();
const parentTurn = new THREE.Quaternion();

// The node index of a VRM's humanoid head bone (VRM 0.x humanBones list, VRM 1.0 map), or null.
function humanoidHead(parser) {
  const ext = (parser && parser.json.extensions) || {};
  const old = ext.VRM && ext.VRM.humanoid && ext.VRM.humanoid.humanBones;
  const found = Array.isArray(old) ? old.find((b) => b.bone === "head") : null;
  if (found) return found.node;
  const bones = ext.VRMC_vrm && ext.VRMC_vrm.humanoid && ext.VRMC_vrm.humanoid.humanBones;
  return bones && bones.head ? bones.head.node : null;
}

function findPoseTarget(root, label, parser) {
  const humanoid = humanoidHead(parser);
  let bone = null;
  root.traverse((o) => {
    const where = parser && parser.associations.get(o);
    if (!bone && humanoid !== null && where && where.nodes === humanoid) bone = o;
  });
  root.traverse((o) => {
    if (!bone && o.isBone && /(^|[_.:])head$/i.test(o.name)) bone = o;
  });
  if (bone) return { bone, rest: bone.quaternion.clone() };
  return label === "head.glb" ? { object: root } : null;
}

function applyPose(pose) {
  if (!pose || !poseTarget) return;
  poseTurn.setFromEuler(poseEuler.set(pose[0], pose[1], pose[2], "YXZ"));
  if (poseTarget.bone) {
    const { bone, rest } = poseTarget;
    if (bone.parent) bone.parent.getWorldQuaternion(parentTurn);
    else parentTurn.identity();
    // world rotation of the bone = turn * parent * rest: its local one in the parent's frame
    bone.quaternion.copy(parentTurn).invert().multiply(poseTurn).multiply(parentTurn).multiply(rest);
  } else {
    poseTarget.object.quaternion.copy(poseTurn);
    poseTarget.object.position.set(pose[3], pose[4], pose[5]);
  }
}

// Show `gltf` (a loaded .glb/.vrm) instead of the current model.
function show(gltf, label) {
  const head = gltf.scene;
  if (talkmesh.head) scene.remove(talkmesh.head);
  rig = new AvatarRig(gltf, talkmesh.names || ARKIT_NAMES);
  scene.add(head);
  talkmesh.head = head;
  frameHead(head);
  poseTarget = findPoseTarget(head, label, gltf.parser);
  const binding = rig.binding;
  const driven = rig.driven.map((mesh) => mesh.userData.talkmeshName);
  talkmesh.avatar = {
    name: label,
    meshes: driven,
    channels: binding.channels,
    missing: binding.missing,
    visemes: binding.visemes,
    expressions: binding.expressions,
    vrm: binding.vrm,
  };
  let summary = `${label}: ${binding.channels.length} of ${ARKIT_NAMES.length} ARKit channels`;
  if (binding.visemes.length) summary += ` + ${binding.visemes.length} visemes`;
  if (binding.expressions.length) summary += ` + VRM ${binding.vrm} presets ${binding.expressions.join(" ")}`;
  $("avatar").textContent = summary;
  $("avatar").title = binding.missing.length ? `lacks ${binding.missing.join(", ")}` : "all 52";
  if (talkmesh.state === "loading" || talkmesh.state === "error") setState("idle");
  if (!driven.length) showError(`${label} has no morph targets with ARKit names, visemes or VRM mouth presets`);
  else showMessage("");
}

// The download bar over the view while a model loads (head.glb is 3 MB: seconds on a slow link).
function showProgress(label, loaded, total) {
  talkmesh.loading = { label, loaded, total };
  talkmesh.loadSteps += 1;
  const mb = (n) => (n / 2 ** 20).toFixed(1);
  const bar = $("progress");
  if (total > 0) {
    bar.max = total;
    bar.value = loaded;
  } else {
    bar.removeAttribute("value"); // indeterminate: the server sent no length
  }
  const part = total > 0 ? `${mb(loaded)} of ${mb(total)} MB (${Math.round((100 * loaded) / total)}%)` : `${mb(loaded)} MB`;
  $("progress-text").textContent = `loading ${label}: ${part}`;
  $("loading").hidden = false;
}

function hideProgress() {
  talkmesh.loading = null;
  $("loading").hidden = true;
}

function load(url, label) {
  showProgress(label, 0, 0);
  new GLTFLoader().load(
    url,
    (gltf) => {
      hideProgress();
      show(gltf, label);
    },
    (e) => showProgress(label, e.loaded, e.lengthComputable ? e.total : 0),
    (err) => {
      hideProgress();
      showError(`could not load ${label}: ${err.message || err}`);
    },
  );
}

// Drag and drop of a .glb/.vrm anywhere on the page.
window.addEventListener("dragover", (e) => e.preventDefault());
window.addEventListener("drop", async (e) => {
  e.preventDefault();
  const file = e.dataTransfer && e.dataTransfer.files[0];
  if (!file) return;
  if (!/\.(glb|vrm)$/i.test(file.name)) {
    showMessage(`${file.name}: drop a .glb or .vrm avatar`);
    return;
  }
  try {
    const buffer = await file.arrayBuffer();
    new GLTFLoader().parse(
      buffer,
      "",
      (gltf) => show(gltf, file.name),
      (err) => showError(`could not load ${file.name}: ${err.message || err}`),
    );
  } catch (err) {
    showError(`could not read ${file.name}: ${err.message || err}`);
  }
});

// --- the stream

// Frames wait here for the next animation frame: at most one stays queued after each display.
let pending = [];

function quantile(sorted, q) {
  const x = (sorted.length - 1) * q;
  const i = Math.floor(x);
  return i + 1 < sorted.length ? sorted[i] + (x - i) * (sorted[i + 1] - sorted[i]) : sorted[i];
}

class Session {
  constructor(model, lookaheadMs) {
    this.sent = []; // {end: samples sent so far including this chunk, at: send time (ms)}
    this.cursor = 0; // frames arrive in order, so the chunk search resumes here
    this.samplesSent = 0;
    this.backlog = []; // chunks captured before the server said hello
    this.ready = false;
    this.finishing = false;
    this.endSentAt = null;
    this.latencies = []; // {at: receive time, ms}
    this.teardown = [];
    this.node = null;
    this.jawIndex = -1;

    const protocol = location.protocol === "https:" ? "wss:" : "ws:";
    const query = new URLSearchParams({ model, lookahead_ms: String(lookaheadMs) });
    this.ws = new WebSocket(`${protocol}//${location.host}/ws/stream?${query}`);
    this.ws.binaryType = "arraybuffer";
    this.ws.onmessage = (e) => this.receive(e.data);
    this.ws.onclose = (e) => this.closed(e);

    Object.assign(talkmesh, {
      framesReceived: 0,
      latencyMs: { median: null, p95: null },
      weightHistory: { jawOpen: [] },
      lastWeights: null,
      endFrames: null,
      error: null,
    });
    pending = [];
    setState("connecting");
  }

  // Route `source` (an AudioNode) through the capture worklet.
  attach(context, source) {
    const node = new AudioWorkletNode(context, "talkmesh-capture", { outputChannelCount: [1] });
    const mute = context.createGain();
    mute.gain.value = 0; // keeps the worklet pulled by the graph without echoing the microphone
    node.connect(mute).connect(context.destination);
    source.connect(node);
    node.port.onmessage = (e) => {
      if (e.data === "finished") this.sendEnd();
      else this.send(e.data);
    };
    this.node = node;
    this.teardown.push(() => {
      source.disconnect(node);
      node.disconnect();
      mute.disconnect();
    });
  }

  send(chunk) {
    if (!this.ready) {
      this.backlog.push(chunk);
      return;
    }
    if (this.ws.readyState !== WebSocket.OPEN) return;
    this.ws.send(chunk);
    this.samplesSent += chunk.byteLength / 2;
    this.sent.push({ end: this.samplesSent, at: performance.now() });
  }

  // End of audio: the worklet sends what it still holds, then says "finished" and we send "end".
  finish() {
    if (this.finishing) return;
    this.finishing = true;
    if (this.node) this.node.port.postMessage("finish");
    else this.sendEnd();
  }

  sendEnd() {
    this.stopAudio();
    if (!this.ready) {
      this.endPending = true;
      return;
    }
    if (this.ws.readyState !== WebSocket.OPEN || this.endSentAt !== null) return;
    this.ws.send(JSON.stringify({ type: "end" }));
    this.endSentAt = performance.now();
    if (talkmesh.state === "streaming") setState("ending");
  }

  stopAudio() {
    for (const undo of this.teardown.splice(0)) {
      try {
        undo();
      } catch {
        // already disconnected
      }
    }
    if (this.node) this.node.port.postMessage("stop");
  }

  close() {
    this.stopAudio();
    if (this.ws.readyState <= WebSocket.OPEN) this.ws.close();
  }

  receive(data) {
    const now = performance.now();
    if (session !== this) return; // a replaced session's last messages
    if (typeof data === "string") {
      this.message(JSON.parse(data));
      return;
    }
    let frame;
    try {
      frame = parseFrame(data);
    } catch (err) {
      this.fail(err.message);
      return;
    }
    if (talkmesh.names && frame.weights.length !== talkmesh.names.length) {
      this.fail(`frame has ${frame.weights.length} weights, hello named ${talkmesh.names.length}`);
      return;
    }
    if (!talkmesh.names) {
      this.fail("frame before hello");
      return;
    }
    talkmesh.framesReceived += 1;
    pending.push(frame);
    if (frame.headPose) talkmesh.headPose = Array.from(frame.headPose);
    const named = {};
    talkmesh.names.forEach((name, i) => (named[name] = frame.weights[i]));
    talkmesh.lastWeights = named;
    if (this.jawIndex >= 0) {
      const history = talkmesh.weightHistory.jawOpen;
      history.push(frame.weights[this.jawIndex]);
      if (history.length > HISTORY_FRAMES) history.splice(0, history.length - HISTORY_FRAMES);
    }
    this.measure(frame.time, now);
    plotDirty = true;
  }

  // Latency = receive time - send time of the chunk holding the audio up to frame time + look-ahead.
  measure(time, now) {
    const needed = Math.max(0, Math.ceil((time + talkmesh.lookaheadMs / 1000) * SAMPLE_RATE - 1e-6) - 1);
    while (this.cursor < this.sent.length && this.sent[this.cursor].end <= needed) this.cursor += 1;
    let sentAt;
    if (this.cursor < this.sent.length) sentAt = this.sent[this.cursor].at;
    else if (this.endSentAt !== null) sentAt = this.endSentAt; // flushed past the end of the audio
    else if (this.sent.length) sentAt = this.sent[this.sent.length - 1].at;
    else return;
    if (this.cursor > 1000) {
      this.sent.splice(0, this.cursor);
      this.cursor = 0;
    }
    this.latencies.push({ at: now, ms: now - sentAt });
    while (this.latencies[0].at < now - LATENCY_WINDOW_MS) this.latencies.shift();
    const sorted = this.latencies.map((l) => l.ms).sort((a, b) => a - b);
    talkmesh.latencyMs = { median: quantile(sorted, 0.5), p95: quantile(sorted, 0.95) };
  }

  message(msg) {
    if (msg.type === "hello") {
      talkmesh.names = msg.names;
      talkmesh.streamFps = msg.fps;
      talkmesh.lookaheadMs = msg.lookahead_ms;
      talkmesh.model = msg.model;
      this.jawIndex = msg.names.indexOf("jawOpen");
      if (rig) rig.bind(msg.names);
      this.ready = true;
      setState(this.finishing ? "ending" : "streaming");
      for (const chunk of this.backlog.splice(0)) this.send(chunk);
      if (this.endPending) this.sendEnd();
    } else if (msg.type === "end") {
      talkmesh.endFrames = msg.frames;
      setState("done");
      this.close();
    } else if (msg.type === "error") {
      this.fail(msg.message);
    }
  }

  fail(message) {
    showError(message);
    this.close();
  }

  closed(event) {
    this.stopAudio();
    if (session !== this) return;
    if (talkmesh.state !== "done" && talkmesh.state !== "error") {
      setState("closed");
      if (event.code !== 1000 && event.code !== 1005) showMessage(`connection closed (${event.code})`);
    }
    updateButtons(false);
  }
}

let session = null;

async function start(kind, file) {
  if (session) session.close();
  showMessage("");
  const current = new Session($("model").value || "procedural", Number($("lookahead").value));
  session = current;
  updateButtons(true);
  try {
    const context = await audio();
    if (kind === "mic") {
      const stream = await navigator.mediaDevices.getUserMedia({
        audio: { channelCount: 1, echoCancellation: false, noiseSuppression: false, autoGainControl: false },
      });
      const source = context.createMediaStreamSource(stream);
      current.attach(context, source);
      current.teardown.push(() => stream.getTracks().forEach((t) => t.stop()));
      current.stopCapture = () => current.finish();
    } else {
      const decoded = await context.decodeAudioData(await file.arrayBuffer());
      const source = context.createBufferSource();
      source.buffer = decoded;
      source.connect(context.destination); // the user hears it while it streams
      current.attach(context, source);
      current.teardown.push(() => source.disconnect());
      source.onended = () => current.finish();
      current.stopCapture = () => source.stop();
      source.start();
    }
  } catch (err) {
    current.fail(err.message || String(err));
  }
}

// --- page

let plotDirty = false;

function setState(state) {
  talkmesh.state = state;
  $("state").textContent = state;
}

function showMessage(text) {
  $("message").textContent = text;
}

function showError(message) {
  talkmesh.error = message;
  setState("error");
  showMessage(message);
}

function updateButtons(running) {
  $("stop").disabled = !running;
}

function fillModels(health) {
  let models = health && health.models;
  if (models && !Array.isArray(models)) models = Object.keys(models);
  if (!models || !models.length) models = ["procedural"];
  const select = $("model");
  select.replaceChildren();
  for (const m of models) {
    const name = typeof m === "string" ? m : m.name;
    select.add(new Option(name, name, false, name === "procedural"));
  }
}

fetch("health")
  .then((r) => r.json())
  .then((health) => {
    fillModels(health);
    if (health.avatar) load("avatar.glb", health.avatar);
    else load("head.glb", "head.glb");
  })
  .catch(() => {
    fillModels(null);
    load("head.glb", "head.glb");
  });

$("mic").addEventListener("click", () => start("mic"));
$("file").addEventListener("change", (e) => {
  const file = e.target.files[0];
  e.target.value = "";
  if (file) start("file", file);
});
$("stop").addEventListener("click", () => {
  if (session && session.stopCapture) session.stopCapture();
  else if (session) session.finish();
  updateButtons(false);
});

function drawPlot() {
  const canvas = $("plot");
  const g = canvas.getContext("2d");
  const values = talkmesh.weightHistory.jawOpen;
  const top = Math.max(0.5, ...values); // jawOpen rarely passes 0.5 in speech
  g.clearRect(0, 0, canvas.width, canvas.height);
  g.strokeStyle = "#8fd3ff";
  g.lineWidth = 1.5;
  g.beginPath();
  values.forEach((v, i) => {
    const x = (i / (HISTORY_FRAMES - 1)) * canvas.width;
    const y = canvas.height - 2 - Math.max(0, v / top) * (canvas.height - 4);
    if (i === 0) g.moveTo(x, y);
    else g.lineTo(x, y);
  });
  g.stroke();
}

function formatMs(x) {
  return x === null ? "\u2013" : `${x.toFixed(0)}`;
}

let fpsSince = performance.now();
let fpsCount = 0;
let statsAt = 0;

function tick(now) {
  // Jitter buffer: drop all but the newest two, show the oldest of them.
  if (pending.length > 2) pending.splice(0, pending.length - 2);
  if (pending.length) {
    const frame = pending.shift();
    if (rig) rig.apply(frame.weights);
    applyPose(frame.headPose);
  }
  controls.update();
  renderer.render(scene, camera);

  fpsCount += 1;
  if (now - fpsSince >= 500) {
    talkmesh.fps = (fpsCount * 1000) / (now - fpsSince);
    fpsSince = now;
    fpsCount = 0;
  }
  if (plotDirty) {
    drawPlot();
    plotDirty = false;
  }
  if (now - statsAt >= STATS_EVERY_MS) {
    statsAt = now;
    const { median, p95 } = talkmesh.latencyMs;
    $("frames").textContent = String(talkmesh.framesReceived);
    $("fps").textContent = `${talkmesh.fps.toFixed(0)} fps`;
    $("latency").textContent = median === null ? "\u2013" : `${formatMs(median)} ms (p95 ${formatMs(p95)})`;
  }
}

renderer.setAnimationLoop(tick);
