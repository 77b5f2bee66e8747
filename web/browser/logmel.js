// Whisper's log-mel spectrogram in the page, the numbers of talkmesh.models.whisper.log_mel:
// periodic Hann window, n_fft 400, hop 160, centred with reflect padding, the last frame dropped,
// power spectrum, Slaney mel filters, log10 clamped to 8 below the peak, then (x + 4) / 4.

export const SAMPLE_RATE = 16000;
const N_FFT = 400;
const HOP = 160;
const BINS = N_FFT / 2 + 1;

// (nMels, BINS) Slaney-scale triangular filters, area-normalised (librosa's defaults).
function melFilters(nMels) {
  const fSp = 200 / 3;
  const minLogHz = 1000;
  const minLogMel = minLogHz / fSp;
  const logstep = Math.log(6.4) / 27;
  const hzToMel = (f) => (f >= minLogHz ? minLogMel + Math.log(f / minLogHz) / logstep : f / fSp);
  const melToHz = (m) => (m >= minLogMel ? minLogHz * Math.exp(logstep * (m - minLogMel)) : fSp * m);
  const top = hzToMel(SAMPLE_RATE / 2);
  const melHz = Array.from({ length: nMels + 2 }, (_, i) => melToHz((top * i) / (nMels + 1)));
  const filters = new Float64Array(nMels * BINS);
  for (let m = 0; m < nMels; m++) {
    const norm = 2 / (melHz[m + 2] - melHz[m]);
    for (let k = 0; k < BINS; k++) {
      const f = ((SAMPLE_RATE / 2) * k) / (BINS - 1);
      const lower = (f - melHz[m]) / (melHz[m + 1] - melHz[m]);
      const upper = (melHz[m + 2] - f) / (melHz[m + 2] - melHz[m + 1]);
      filters[m * BINS + k] = Math.max(0, Math.min(lower, upper)) * norm;
    }
  }
  return filters;
}

// One frame's log10 mel power: the tables made once.
class Spectrum {
  constructor(nMels) {
    this.nMels = nMels;
    this.window = Float64Array.from({ length: N_FFT }, (_, i) => 0.5 - 0.5 * Math.cos((2 * Math.PI * i) / N_FFT));
    this.cos = new Float64Array(BINS * N_FFT);
    this.sin = new Float64Array(BINS * N_FFT);
    for (let k = 0; k < BINS; k++) {
      for (let i = 0; i < N_FFT; i++) {
        const a = (2 * Math.PI * k * i) / N_FFT;
        this.cos[k * N_FFT + i] = Math.cos(a);
        this.sin[k * N_FFT + i] = Math.sin(a);
      }
    }
    this.filters = melFilters(nMels);
    this.frame = new Float64Array(N_FFT);
    this.power = new Float64Array(BINS);
  }

  // log10 mel power of the N_FFT samples sample(0..N_FFT-1) into out[m * stride + at]; its peak.
  run(sample, out, stride, at) {
    const { frame, power, cos, sin, filters, window } = this;
    for (let i = 0; i < N_FFT; i++) frame[i] = sample(i) * window[i];
    for (let k = 0; k < BINS; k++) {
      let re = 0;
      let im = 0;
      const row = k * N_FFT;
      for (let i = 0; i < N_FFT; i++) {
        re += frame[i] * cos[row + i];
        im -= frame[i] * sin[row + i];
      }
      power[k] = re * re + im * im;
    }
    let peak = -Infinity;
    for (let m = 0; m < this.nMels; m++) {
      let s = 0;
      for (let k = 0; k < BINS; k++) s += filters[m * BINS + k] * power[k];
      const v = Math.log10(Math.max(s, 1e-10));
      out[m * stride + at] = v;
      if (v > peak) peak = v;
    }
    return peak;
  }
}

// audio: Float32Array at 16 kHz -> Float32Array (nMels, frames) row-major, and frames.
export function logMel(audio, nMels = 80) {
  const pad = N_FFT / 2;
  const n = audio.length;
  const padded = new Float64Array(n + 2 * pad);
  for (let i = 0; i < padded.length; i++) {
    let j = i - pad;
    if (j < 0) j = -j;
    if (j >= n) j = 2 * (n - 1) - j;
    padded[i] = audio[j];
  }
  const frames = Math.floor(n / HOP); // 1 + n // HOP frames, the last one dropped
  const spectrum = new Spectrum(nMels);
  const spec = new Float64Array(nMels * frames);
  let peak = -Infinity;
  for (let t = 0; t < frames; t++) {
    peak = Math.max(peak, spectrum.run((i) => padded[t * HOP + i], spec, frames, t));
  }
  const out = new Float32Array(nMels * frames);
  for (let i = 0; i < out.length; i++) out[i] = (Math.max(spec[i], peak - 8) + 4) / 4;
  return { mel: out, frames };
}

// The log-mel of a stream (a microphone), frame by frame as its samples arrive: frame m once
// samples up to m * HOP + N_FFT / 2 have come (the start reflect-padded as logMel pads it), so
// every frame equals logMel's of the whole recording; the clamp is 8 below the peak heard so far.
// Frames older than `keep` are let go.
export class MelStream {
  constructor(nMels = 80, keep = 30 * 100) {
    this.spectrum = new Spectrum(nMels);
    this.nMels = nMels;
    this.keep = keep;
    this.audio = new Float32Array(0); // samples from audioStart on
    this.audioStart = 0;
    this.log = []; // Float64Array(nMels) per frame, from logStart on
    this.logStart = 0;
    this.frames = 0; // frames computed
    this.peak = -Infinity;
  }

  push(samples) {
    const joined = new Float32Array(this.audio.length + samples.length);
    joined.set(this.audio);
    joined.set(samples, this.audio.length);
    this.audio = joined;
    const pad = N_FFT / 2;
    const total = this.audioStart + this.audio.length;
    while (this.frames * HOP + pad <= total) {
      const first = this.frames * HOP - pad;
      const column = new Float64Array(this.nMels);
      const sample = (i) => this.audio[Math.abs(first + i) - this.audioStart];
      this.peak = Math.max(this.peak, this.spectrum.run(sample, column, 1, 0));
      this.log.push(column);
      this.frames++;
    }
    const drop = Math.max(0, this.frames * HOP - pad - this.audioStart - N_FFT);
    if (drop > 0 && this.audioStart + drop > pad) {
      this.audio = this.audio.slice(drop);
      this.audioStart += drop;
    }
    if (this.log.length > this.keep) {
      const n = this.log.length - this.keep;
      this.log.splice(0, n);
      this.logStart += n;
    }
  }

  // Frames m0 <= m < m1 as logMel normalises them -> Float32Array (nMels, m1 - m0) row-major.
  window(m0, m1) {
    if (m0 < this.logStart || m1 > this.frames) throw new Error(`mel frames ${m0}..${m1} are not held`);
    const width = m1 - m0;
    const out = new Float32Array(this.nMels * width);
    for (let t = 0; t < width; t++) {
      const column = this.log[m0 + t - this.logStart];
      for (let m = 0; m < this.nMels; m++) out[m * width + t] = (Math.max(column[m], this.peak - 8) + 4) / 4;
    }
    return out;
  }
}
