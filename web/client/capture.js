// Audio capture shared by the viewer, talkmesh-client and the in-browser page: an AudioWorklet that
// mixes to mono, resamples to `rate` (16 kHz, the models' rate) and posts int16 chunks of `chunk`
// samples. Linear interpolation after a 4th-order Butterworth low-pass (two biquads, RBJ
// cookbook) at 0.45x the output rate, so that 44.1/48 kHz input does not alias into the stream.
// The node takes "finish" (post what it holds, then "finished") and "stop".

export function captureWorklet(rate, chunk) {
  return `
const TARGET_RATE = ${rate};
const CHUNK = ${chunk};

class LowPass {
  constructor(cutoff, q) {
    const w0 = (2 * Math.PI * cutoff) / sampleRate;
    const alpha = Math.sin(w0) / (2 * q);
    const cos = Math.cos(w0);
    const a0 = 1 + alpha;
    this.b0 = (1 - cos) / 2 / a0;
    this.b1 = (1 - cos) / a0;
    this.b2 = this.b0;
    this.a1 = (-2 * cos) / a0;
    this.a2 = (1 - alpha) / a0;
    this.z1 = 0;
    this.z2 = 0;
  }
  run(x) {
    for (let i = 0; i < x.length; i++) {
      const v = x[i];
      const y = this.b0 * v + this.z1;
      this.z1 = this.b1 * v - this.a1 * y + this.z2;
      this.z2 = this.b2 * v - this.a2 * y;
      x[i] = y;
    }
  }
}

class Capture extends AudioWorkletProcessor {
  constructor() {
    super();
    this.step = sampleRate / TARGET_RATE;
    const cutoff = 0.45 * TARGET_RATE;
    this.filters = this.step > 1 ? [new LowPass(cutoff, 0.5412), new LowPass(cutoff, 1.3066)] : [];
    this.t = 0; // position of the next output sample, in input samples from the block start
    this.prev = 0; // last input sample of the previous block (position -1)
    this.mono = new Float32Array(128);
    this.out = new Int16Array(CHUNK);
    this.fill = 0;
    this.running = true;
    this.port.onmessage = (e) => {
      if (e.data === "finish") this.finish();
      else if (e.data === "stop") this.running = false;
    };
  }

  process(inputs) {
    const input = inputs[0];
    if (!this.running || input.length === 0) return this.running;
    const n = input[0].length;
    if (this.mono.length !== n) this.mono = new Float32Array(n);
    const x = this.mono;
    x.fill(0);
    for (const channel of input) for (let i = 0; i < n; i++) x[i] += channel[i] / input.length;
    for (const f of this.filters) f.run(x);
    let t = this.t;
    while (t <= n - 1) {
      const i = Math.floor(t);
      const f = t - i;
      const a = i < 0 ? this.prev : x[i];
      this.push(f === 0 ? a : a + f * (x[i + 1] - a));
      t += this.step;
    }
    this.t = t - n;
    this.prev = x[n - 1];
    return true;
  }

  push(v) {
    this.out[this.fill++] = Math.round(Math.max(-1, Math.min(1, v)) * 32767);
    if (this.fill === CHUNK) {
      this.port.postMessage(this.out.buffer, [this.out.buffer]);
      this.out = new Int16Array(CHUNK);
      this.fill = 0;
    }
  }

  finish() {
    if (this.fill > 0) this.port.postMessage(this.out.slice(0, this.fill).buffer);
    this.fill = 0;
    this.running = false;
    this.port.postMessage("finished");
  }
}

registerProcessor("talkmesh-capture", Capture);
`;
}

// Register the worklet on `context` (once per context) under the name "talkmesh-capture".
export async function addCapture(context, rate, chunk) {
  if (context.talkmeshCapture) return;
  const url = URL.createObjectURL(new Blob([captureWorklet(rate, chunk)], { type: "text/javascript" }));
  try {
    await context.audioWorklet.addModule(url);
  } finally {
    URL.revokeObjectURL(url);
  }
  context.talkmeshCapture = true;
}

// Route `source` (an AudioNode) through the capture worklet, muted (the graph pulls the worklet
// without echoing a microphone). onChunk(ArrayBuffer of int16) per chunk; returns {node, close}.
export function openCapture(context, source, onChunk, onFinished = () => {}) {
  const node = new AudioWorkletNode(context, "talkmesh-capture", { outputChannelCount: [1] });
  const mute = context.createGain();
  mute.gain.value = 0;
  node.connect(mute).connect(context.destination);
  source.connect(node);
  node.port.onmessage = (e) => {
    if (e.data === "finished") onFinished();
    else onChunk(e.data);
  };
  let open = true;
  const close = () => {
    if (!open) return;
    open = false;
    node.port.postMessage("stop");
    source.disconnect(node);
    node.disconnect();
    mute.disconnect();
  };
  return { node, close };
}

// The microphone as a MediaStream, its processing off (the models heard raw speech); a refusal
// or a missing device is an Error whose message is one line saying what to do.
export async function microphone() {
  if (!navigator.mediaDevices || !navigator.mediaDevices.getUserMedia) {
    throw new Error("this page cannot use a microphone here (it needs https or localhost)");
  }
  try {
    return await navigator.mediaDevices.getUserMedia({
      audio: { channelCount: 1, echoCancellation: false, noiseSuppression: false, autoGainControl: false },
    });
  } catch (e) {
    if (e.name === "NotAllowedError" || e.name === "SecurityError") {
      throw new Error("the microphone was refused: allow it in the browser's site settings, or load a speech file");
    }
    if (e.name === "NotFoundError" || e.name === "OverconstrainedError") {
      throw new Error("no microphone found: plug one in, or load a speech file");
    }
    throw new Error(`the microphone cannot start (${e.name}: ${e.message})`);
  }
}
