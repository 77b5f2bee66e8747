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
  const window = Float64Array.from({ length: N_FFT }, (_, i) => 0.5 - 0.5 * Math.cos((2 * Math.PI * i) / N_FFT));
  const cos = new Float64Array(BINS * N_FFT);
  const sin = new Float64Array(BINS * N_FFT);
  for (let k = 0; k < BINS; k++) {
    for (let i = 0; i < N_FFT; i++) {
      const a = (2 * Math.PI * k * i) / N_FFT;
      cos[k * N_FFT + i] = Math.cos(a);
      sin[k * N_FFT + i] = Math.sin(a);
    }
  }
  const filters = melFilters(nMels);
  const spec = new Float64Array(nMels * frames);
  const frame = new Float64Array(N_FFT);
  const power = new Float64Array(BINS);
  let peak = -Infinity;
  for (let t = 0; t < frames; t++) {
    for (let i = 0; i < N_FFT; i++) frame[i] = padded[t * HOP + i] * window[i];
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
    for (let m = 0; m < nMels; m++) {
      let s = 0;
      for (let k = 0; k < BINS; k++) s += filters[m * BINS + k] * power[k];
      const v = Math.log10(Math.max(s, 1e-10));
      spec[m * frames + t] = v;
      if (v > peak) peak = v;
    }
  }
  const out = new Float32Array(nMels * frames);
  for (let i = 0; i < out.length; i++) out[i] = (Math.max(spec[i], peak - 8) + 4) / 4;
  return { mel: out, frames };
}
