// talkmesh-client: speech in, ARKit weights out, played on any three.js object in step with the
// audio. No dependency (three.js is the page's own): meshes are found by their morph targets
// (three.js's Mesh and SkinnedMesh, a VRM's scene), names matched as talkmesh.face.arkit_names
// matches them; an avatar without ARKit mouth shapes is driven through its VRM mouth presets (pass
// the loader's gltf, whose parser holds the VRM extension) or its Oculus visemes (AvatarRig).
//
//   const client = new TalkmeshClient("ws://127.0.0.1:8000/ws/stream");
//   client.attach(gltf);                      // or gltf.scene, vrm.scene: any three.js object
//   await client.playAudio(audioBuffer);      // an AudioBuffer: plays it and animates in step
//   await client.streamMicrophone();          // or the microphone, live, until stopMicrophone()
//   client.update();                          // every animation frame
//
// The protocol (docs/guide/streaming.md): 16 kHz mono int16 PCM in binary messages, then
// {"type": "end"}; the server answers a hello, one "TMF1" binary message per frame and an end.

import { ARKIT_NAMES } from "./arkit_names.js";
import { AvatarRig } from "./avatar.js";
import { addCapture, microphone, openCapture } from "./capture.js";

export { ARKIT_NAMES, VISEMES, VRM_PRESETS, bindAvatar } from "./arkit_names.js";
export { AvatarRig, targetNames } from "./avatar.js";
export { addCapture, microphone, openCapture } from "./capture.js";

export const SAMPLE_RATE = 16000;
const CHUNK_SAMPLES = SAMPLE_RATE / 10; // 100 ms per message
const FRAME_MAGIC = 0x544d4631; // "TMF1" read big-endian
const HEADER_BYTES = 16;

const FLAG_HEAD = 2;

// One frame message -> {index, time, flags, weights: Float32Array, headPose} (weights in
// hello.names order; headPose: Float32Array [pitch, yaw, roll (radians), x, y, z (metres)] or
// null, a vertex v going to R v + t with R = Ry(yaw) Rx(pitch) Rz(roll), three.js's Euler order
// "YXZ"). Throws on a message that is not a frame or is cut short.
export function parseFrame(buffer) {
  const view = new DataView(buffer);
  if (buffer.byteLength < HEADER_BYTES || view.getUint32(0, false) !== FRAME_MAGIC) {
    throw new Error("not a talkmesh frame (TMF1)");
  }
  const count = view.getUint16(12, true);
  const flags = view.getUint16(14, true);
  const poseAt = HEADER_BYTES + 4 * count;
  if (buffer.byteLength < poseAt + (flags & FLAG_HEAD ? 24 : 0)) throw new Error("truncated frame");
  const weights = new Float32Array(count);
  for (let i = 0; i < count; i++) weights[i] = view.getFloat32(HEADER_BYTES + 4 * i, true);
  let headPose = null;
  if (flags & FLAG_HEAD) {
    headPose = new Float32Array(6);
    for (let i = 0; i < 6; i++) headPose[i] = view.getFloat32(poseAt + 4 * i, true);
  }
  return { index: view.getUint32(4, true), time: view.getFloat32(8, true), flags, weights, headPose };
}

// (S,) float samples at `rate` -> 16 kHz int16, through an OfflineAudioContext (the browser's
// own resampler, with its anti-aliasing filter).
export async function toPcm16(buffer) {
  const frames = Math.ceil(buffer.duration * SAMPLE_RATE);
  const offline = new OfflineAudioContext(1, Math.max(1, frames), SAMPLE_RATE);
  const source = offline.createBufferSource();
  source.buffer = buffer;
  source.connect(offline.destination);
  source.start();
  const mono = (await offline.startRendering()).getChannelData(0);
  const pcm = new Int16Array(mono.length);
  for (let i = 0; i < mono.length; i++) pcm[i] = Math.max(-32768, Math.min(32767, Math.round(mono[i] * 32767)));
  return pcm;
}

export class TalkmeshClient {
  // url: the server's ws://HOST:PORT/ws/stream (query options: model, lookahead_ms, livelink).
  constructor(url, { audioContext } = {}) {
    this.url = url;
    this.context = audioContext || new AudioContext();
    this.rig = null; // the attached object's AvatarRig
    this.frames = []; // received, not yet shown
    this.names = ARKIT_NAMES;
    this.start = null; // the AudioContext time of frame 0
    this.state = "idle";
    this.received = 0;
    this.shown = []; // [frame time, audio time when shown] of every frame shown
    this.onframe = null; // called with each frame as it is shown
  }

  // Drive every mesh under `avatar` (a GLTFLoader result, or any three.js object) whose morph
  // targets carry ARKit names, Oculus visemes or, from a .vrm's gltf, VRM mouth presets. Returns
  // how many morph targets it drives.
  attach(avatar) {
    this.rig = new AvatarRig(avatar, this.names);
    return this.rig.targetCount();
  }

  // Play `buffer` (an AudioBuffer) and stream it to the server: the frames are shown as the
  // audio reaches their time. Resolves with the number of frames once the server has ended.
  async playAudio(buffer) {
    this.live = false;
    const pcm = await toPcm16(buffer);
    return this._stream((ws) => {
      for (let i = 0; i < pcm.length; i += CHUNK_SAMPLES) ws.send(pcm.slice(i, i + CHUNK_SAMPLES).buffer);
      ws.send(JSON.stringify({ type: "end" }));
      const source = this.context.createBufferSource();
      source.buffer = buffer;
      source.connect(this.context.destination);
      this.start = this.context.currentTime + 0.05; // a frame's time is from here
      source.start(this.start);
      source.onended = () => { this.playing = false; }; // prettier-ignore
      this.playing = true;
    });
  }

  // Stream the microphone (resampled to 16 kHz in an AudioWorklet) until stopMicrophone(); each
  // frame is shown as soon as it arrives. Resolves with the number of frames once the server has
  // ended; a refused or missing microphone rejects with a one-line Error.
  async streamMicrophone() {
    await this.context.resume();
    const stream = await microphone();
    await addCapture(this.context, SAMPLE_RATE, CHUNK_SAMPLES);
    const source = this.context.createMediaStreamSource(stream);
    this.live = true;
    this.latencies = []; // ms from sending a frame's audio to receiving the frame
    this.sent = []; // [samples sent so far, performance.now()]
    let samples = 0;
    let capture = null;
    const stop = () => {
      stream.getTracks().forEach((t) => t.stop());
      if (capture) capture.close();
    };
    this.stopMicrophone = () => {
      if (capture) capture.node.port.postMessage("finish"); // what it holds, then "end"
      else stop();
    };
    try {
      return await this._stream((ws) => {
        capture = openCapture(
          this.context,
          source,
          (chunk) => {
            if (ws.readyState !== WebSocket.OPEN) return;
            ws.send(chunk);
            samples += chunk.byteLength / 2;
            this.sent.push([samples, performance.now()]);
          },
          () => {
            if (ws.readyState === WebSocket.OPEN) ws.send(JSON.stringify({ type: "end" }));
            stop();
          },
        );
      });
    } finally {
      stop();
    }
  }

  // Connect, then begin(ws) once the server said hello; frames are queued for update().
  _stream(begin) {
    const ws = new WebSocket(this.url);
    ws.binaryType = "arraybuffer";
    this.state = "connecting";
    return new Promise((resolve, reject) => {
      ws.onmessage = (event) => {
        if (typeof event.data !== "string") {
          const frame = parseFrame(event.data);
          if (this.live) this._measure(frame);
          this.frames.push(frame);
          this.received++;
          return;
        }
        const message = JSON.parse(event.data);
        if (message.type === "hello") {
          this.names = message.names;
          this.fps = message.fps;
          if (this.rig) this.rig.bind(this.names);
          this.state = "streaming";
          begin(ws);
        } else if (message.type === "end") {
          this.state = "done";
          resolve(message.frames);
        } else if (message.type === "error") {
          this.state = "error";
          reject(new Error(message.message));
        }
      };
      ws.onerror = () => reject(new Error(`cannot reach ${this.url}`));
      ws.onclose = (event) => {
        if (this.state !== "done") reject(new Error(`closed (${event.code}) ${event.reason}`));
      };
    });
  }

  // A live frame's latency: from when the audio up to its end was sent to now.
  _measure(frame) {
    const end = Math.round((frame.time + 1 / this.fps) * SAMPLE_RATE);
    while (this.sent.length > 1 && this.sent[1][0] <= end) this.sent.shift();
    const hit = this.sent.find(([n]) => n >= end);
    if (hit) this.latencies.push(performance.now() - hit[1]);
  }

  // Show the latest frame whose time the audio has reached; call every animation frame.
  // Live (the microphone): the newest frame received.
  update() {
    if ((this.start === null && !this.live) || !this.frames.length) return;
    const now = this.live ? Infinity : this.context.currentTime - this.start;
    let frame = null;
    while (this.frames.length && this.frames[0].time <= now) frame = this.frames.shift();
    if (!frame) return;
    if (this.rig) this.rig.apply(frame.weights);
    this.shown.push([frame.time, this.live ? frame.time : now]);
    if (this.onframe) this.onframe(frame);
  }
}
