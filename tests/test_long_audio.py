"""Long audio: generation and writing a chunk of frames at a time give the frames of the whole-audio
path (small chunks on short clips, so the tests are fast), and the compact .npz reads back within
its stated error, as do the files older talkmesh versions wrote."""

from __future__ import annotations

import zipfile
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from fixtures import TINY_WHISPER

from talkmesh.animation import Animation, AnimationBlocks
from talkmesh.errors import TalkmeshError
from talkmesh.models.codetalker.generate import AheadWindow
from talkmesh.models.codetalker.model import CodeTalker
from talkmesh.models.release import save_model
from talkmesh.models.speech import SpeechEncoderConfig, WhisperEncoder
from talkmesh.models.speech_chunks import FrameFeatures
from talkmesh.output.formats import load_animation, save_animation
from talkmesh.output.streaming import save_blocks
from talkmesh.pipeline import animate_blocks

SPEECH = Path(__file__).parent / "fixtures" / "official" / "speech.wav"
V = 20


def tiny_whisper(window: int) -> WhisperEncoder:
    """A random Whisper encoder whose windows are ``window`` features (20 ms each) long."""
    pytest.importorskip("transformers")
    torch.manual_seed(0)
    enc = WhisperEncoder(SpeechEncoderConfig(kind="whisper", hf_config=TINY_WHISPER)).eval()
    enc.features.window = window
    return enc


def test_whisper_features_window_by_window_equal_the_whole_audio():
    enc = tiny_whisper(window=7)  # 0.14 s windows: the 1.3 s clip spans ten of them
    audio = torch.from_numpy(np.random.default_rng(0).standard_normal(20_777).astype(np.float32))
    audio = audio[None] * 0.1
    with torch.inference_mode():
        whole = enc(audio, None, 41)
        chunked = FrameFeatures(enc, audio, 41)
        parts = torch.cat([chunked(a, min(a + 6, 41)) for a in range(0, 41, 6)], dim=1)
        held = len(chunked.rows.cache)
    torch.testing.assert_close(parts, whole, atol=1e-5, rtol=1e-5)
    assert held <= 2  # only the windows of the last slice are kept
    # the audio is read where it is: no copy padded to whole windows (an hour is 230 MB)
    assert chunked.rows.audio.data_ptr() == audio.data_ptr()
    assert chunked.rows.length == 65 * 320  # 20 777 samples zero-padded to whole 20 ms features


def test_ahead_window_loads_ahead_and_forgets_behind():
    loads = []

    def load(a, b):
        loads.append((a, b))
        return [torch.arange(a, b)[None]]

    window = AheadWindow(load, chunk=5, total=12)
    assert window(0, 1)[0].tolist() == [[0]] and loads == [(0, 5)]
    assert window(1, 4)[0].tolist() == [[1, 2, 3]] and loads == [(0, 5)]
    assert window(4, 7)[0].tolist() == [[4, 5, 6]] and loads[-1] == (5, 10)
    assert window.start == 4  # frames before the pass are gone
    assert window(10, 12)[0].tolist() == [[10, 11]] and loads[-1] == (10, 12)


@pytest.mark.parametrize("kind", ["mel", "whisper"])
def test_codetalker_chunks_equal_whole_generation(kind, tiny_codetalker):
    speech = SpeechEncoderConfig(kind="mel", dim=16)
    if kind == "whisper":
        pytest.importorskip("transformers")
        speech = SpeechEncoderConfig(kind="whisper", hf_config=TINY_WHISPER)
    model = tiny_codetalker(causal=True, attention_window=7, speech=speech)
    if kind == "whisper":
        model.speech.features.window = 9
    audio = torch.from_numpy(np.random.default_rng(1).standard_normal(24_000).astype(np.float32))
    audio = 0.1 * audio[None]
    template = torch.randn(1, V, 3)
    weights = torch.tensor([[0.3, 0.7]])
    whole = model.generate(audio, template, style_weights=weights)
    chunks = list(model.generate_chunks(audio, template, style_weights=weights, chunk=4))
    assert all(c.shape[1] >= 4 for c in chunks[:-1])
    torch.testing.assert_close(torch.cat(chunks, dim=1), whole, atol=1e-5, rtol=1e-5)


def test_procedural_blocks_equal_one_block():
    small = animate_blocks(SPEECH, model="procedural", block=7)
    one = animate_blocks(SPEECH, model="procedural", block=10_000).collect()
    got = small.collect()
    # equal to float32 rounding (7e-9 m apart on numpy 2.4 / scipy 1.17: sums over blocks of
    # other lengths may take another order); a block boundary error would be millimetres
    np.testing.assert_allclose(got.vertices, one.vertices, rtol=0, atol=1e-7)
    np.testing.assert_allclose(got.weights, one.weights, rtol=0, atol=1e-6)


@pytest.mark.parametrize("fps", [30.0, 24.0])
def test_learned_blocks_equal_one_block(tmp_path, fps, tiny_codetalker):
    from talkmesh.face.assets import load_head

    head = load_head()
    model = tiny_codetalker(causal=True, attention_window=7)
    model = CodeTalker(replace(model.cfg, vq=replace(model.cfg.vq, num_vertices=head.num_vertices)))
    path = save_model(model.eval(), tmp_path / "m.safetensors")
    one = animate_blocks(SPEECH, model=str(path), fps=fps, block=10_000).collect()
    got = animate_blocks(SPEECH, model=str(path), fps=fps, block=5).collect()
    assert got.num_frames == one.num_frames == round(1.298 * fps)
    np.testing.assert_allclose(got.vertices, one.vertices, atol=1e-6)
    np.testing.assert_allclose(got.weights, one.weights, atol=1e-5)


def test_learned_blocks_correct_the_mouth_as_the_whole_clip(tmp_path, tiny_codetalker):
    """Blocks of 2 frames with every mouth correction on give the bare whole clip corrected at
    once (face/corrections.correct_mouth); the corrections change the frames."""
    from talkmesh.audio.loading import load_audio
    from talkmesh.audio.phonemes import recognize_phones
    from talkmesh.face.assets import load_head
    from talkmesh.face.corrections import Corrections, correct_mouth
    from talkmesh.pipeline import animate

    head = load_head()
    model = tiny_codetalker(causal=True, attention_window=7)
    model = CodeTalker(replace(model.cfg, vq=replace(model.cfg.vq, num_vertices=head.num_vertices)))
    path = str(save_model(model.eval(), tmp_path / "m.safetensors"))
    every = Corrections(pause_gate=True, lip_closure=True, mix=0.5, gain=0.3)
    got = animate_blocks(
        SPEECH,
        model=path,
        blinks=False,
        lip_closure=True,
        procedural_mix=0.5,
        loudness_gain=0.3,
        block=2,
    ).collect()
    bare = animate(
        SPEECH,
        model=path,
        blinks=False,
        pause_gate=False,
        procedural_mix=0.0,
        loudness_gain=0.0,
        bilabial_closure=False,
    )
    wave = load_audio(SPEECH)
    whole = correct_mouth(bare.vertices.copy(), head, recognize_phones(wave), wave, 30.0, every)
    np.testing.assert_allclose(got.vertices, whole, rtol=0, atol=1e-6)
    assert np.abs(whole - bare.vertices).max() > 1e-4


def _anim(frames: int = 9) -> Animation:
    rng = np.random.default_rng(2)
    template = rng.standard_normal((V, 3)).astype(np.float32) * 0.1
    offsets = rng.uniform(-0.02, 0.02, (frames, V, 3)).astype(np.float32)
    return Animation(
        vertices=template + offsets,
        faces=np.array([[0, 1, 2], [2, 3, 4]]),
        fps=30.0,
        audio=np.zeros(16000, np.float32),
        weights=rng.uniform(0, 1, (frames, 2)).astype(np.float32),
        weight_names=["a", "b"],
        template=template,
    )


def test_npz_stores_float16_offsets_within_the_stated_error(tmp_path):
    anim = _anim()
    save_animation(anim, tmp_path / "a.npz")
    with zipfile.ZipFile(tmp_path / "a.npz") as z:
        assert {i.compress_type for i in z.infolist()} == {zipfile.ZIP_DEFLATED}
    with np.load(tmp_path / "a.npz") as z:
        assert int(z["format_version"]) == 2 and z["offsets"].dtype == np.float16
        assert "vertices" not in z.files
    back = load_animation(tmp_path / "a.npz")
    err = np.abs(back.vertices - anim.vertices)
    assert err.max() <= 0.02 * 2.0**-11 + 1e-7  # half a float16 step of the largest offset
    assert err.max() > 0  # lossy, as documented
    np.testing.assert_array_equal(back.weights, anim.weights)
    assert back.weight_names == ["a", "b"] and back.fps == 30.0


def test_npz_of_older_versions_and_without_template_still_load(tmp_path):
    anim = _anim()
    np.savez(  # format 1, as talkmesh wrote it before
        tmp_path / "old.npz",
        format_version=np.int64(1),
        vertices=anim.vertices,
        faces=anim.faces,
        fps=np.float64(30.0),
        weights=anim.weights,
        weight_names=np.array(anim.weight_names),
    )
    old = load_animation(tmp_path / "old.npz")
    np.testing.assert_array_equal(old.vertices, anim.vertices)
    bare = replace(anim, template=None)
    save_animation(bare, tmp_path / "bare.npz")
    np.testing.assert_array_equal(load_animation(tmp_path / "bare.npz").vertices, anim.vertices)
    with np.load(tmp_path / "bare.npz") as z:
        assert z["vertices"].dtype == np.float32
    np.savez(tmp_path / "newer.npz", format_version=np.int64(3), vertices=anim.vertices,
             faces=anim.faces, fps=np.float64(30.0))  # fmt: skip
    with pytest.raises(TalkmeshError, match="newer talkmesh"):
        load_animation(tmp_path / "newer.npz")


def test_save_blocks_streams_npz_and_npy_and_collects_the_rest(tmp_path):
    anim = _anim(frames=11)

    def blocks(size: int) -> AnimationBlocks:
        parts = (
            Animation(
                anim.vertices[t : t + size],
                anim.faces,
                anim.fps,
                weights=anim.weights[t : t + size],
                weight_names=anim.weight_names,
            )
            for t in range(0, anim.num_frames, size)
        )
        return AnimationBlocks(
            parts, anim.num_frames, anim.faces, anim.fps, audio=anim.audio,
            weight_names=anim.weight_names, template=anim.template,
        )  # fmt: skip

    paths = [tmp_path / "s.npz", tmp_path / "s.npy", tmp_path / "s.obj"]
    assert save_blocks(blocks(3), paths[:2], overwrite=False) is None
    whole = save_blocks(blocks(4), [paths[2]], overwrite=False)
    assert whole is not None and whole.num_frames == 11
    save_animation(anim, tmp_path / "w.npz")
    streamed, direct = load_animation(paths[0]), load_animation(tmp_path / "w.npz")
    np.testing.assert_array_equal(streamed.vertices, direct.vertices)
    np.testing.assert_array_equal(streamed.weights, direct.weights)
    npy = np.load(paths[1])
    np.testing.assert_array_equal(npy, anim.vertices.reshape(11, -1))
    assert (paths[0].stat().st_mode & 0o777) == ((tmp_path / "w.npz").stat().st_mode & 0o777)
    with pytest.raises(TalkmeshError, match="already exists"):
        save_blocks(blocks(3), [paths[0]], overwrite=False)
    names = {p.name for p in tmp_path.iterdir()}
    assert {"s.npz", "s.npy", "s_00010.obj", "w.npz"} <= names
    assert not [n for n in names if n.startswith(".")]  # no temporaries left behind


def test_weight_files_from_blocks_equal_the_whole_animation(tmp_path):
    from talkmesh.pipeline import animate

    paths = [tmp_path / "b.json", tmp_path / "b.csv"]
    got = save_blocks(animate_blocks(SPEECH, model="procedural", block=7), paths, overwrite=False)
    assert got is None  # weight files need no vertices
    whole = animate(SPEECH, model="procedural")
    for p in paths:
        (ref,) = save_animation(whole, tmp_path / f"ref{p.suffix}")
        assert p.read_text() == ref.read_text()


def test_weights_npz_is_the_blend_exact_for_the_procedural_animator(tmp_path):
    from talkmesh.pipeline import animate

    anim = animate(SPEECH, model="procedural")
    (small,) = save_animation(anim, tmp_path / "s.weights.npz")
    (full,) = save_animation(anim, tmp_path / "s.npz")
    with np.load(small) as z:
        assert "offsets" not in z.files and "vertices" not in z.files
    assert small.stat().st_size < full.stat().st_size
    back = load_animation(small)
    np.testing.assert_allclose(back.vertices, anim.vertices, atol=1e-6)
    np.testing.assert_array_equal(back.weights, anim.weights)
    streamed = tmp_path / "b.weights.npz"
    save_blocks(animate_blocks(SPEECH, model="procedural", block=7), [streamed], overwrite=False)
    np.testing.assert_array_equal(load_animation(streamed).vertices, back.vertices)
    with pytest.raises(TalkmeshError, match="needs ARKit weights"):
        save_animation(_anim(), tmp_path / "toy.weights.npz")  # weights without a basis


def test_long_audio_is_recognised_as_utterances_cut_in_pauses(monkeypatch):
    from talkmesh.audio import phonemes
    from talkmesh.audio.loading import load_audio

    clip = load_audio(SPEECH)
    pause = np.zeros(4000, np.float32)  # 0.25 s
    audio = np.concatenate([clip, pause, clip, pause, clip])
    monkeypatch.setattr(phonemes, "UTTERANCE_MAX_S", 2.0)
    monkeypatch.setattr(phonemes, "CUT_SEARCH_S", 1.0)
    spans = phonemes._utterances(audio)
    n = -(-len(audio) // phonemes.SAMPLES_PER_FRAME)
    assert len(spans) >= 2 and spans[0][0] == 0 and spans[-1][1] == n
    assert all(a[1] == b[0] for a, b in zip(spans, spans[1:], strict=False))  # contiguous
    assert all(hi - lo <= 200 for lo, hi in spans)
    rms = phonemes._frame_rms(audio)
    assert all(rms[hi] < 1e-6 for _, hi in spans[:-1])  # every cut in a pause
    phones = phonemes.recognize_phones(audio)
    assert phones[0].start == 0 and abs(phones[-1].end - len(audio) / 16000) < 0.02
    assert sum(p.label != "SIL" for p in phones) > 10


def test_frame_db_in_blocks_equals_the_whole_clip():
    from talkmesh.face.pauses import frame_db

    wave = np.random.default_rng(0).normal(0, 0.1, 16_000 * 3 + 77).astype(np.float32)
    whole = frame_db(wave, block=10**9)
    assert whole.shape == (300,)
    for block in (1, 7, 299, 300):
        np.testing.assert_array_equal(frame_db(wave, block=block), whole)


@pytest.mark.parametrize(
    "sr, channels, subtype", [(16_000, 1, "PCM_16"), (44_100, 2, "PCM_16"), (8_000, 1, "FLOAT")]
)
def test_waveform_slices_equal_the_whole_file_read(tmp_path, sr, channels, subtype):
    """A Waveform's slices are load_audio's, also across resampling and at either end."""
    import soundfile as sf

    from talkmesh.audio.loading import load_audio
    from talkmesh.audio.waveform import Waveform

    rng = np.random.default_rng(1)
    x = rng.normal(0, 0.2, (sr * 2 + 123, channels)).clip(-1, 1).astype(np.float32)
    path = tmp_path / "x.wav"
    sf.write(path, x, sr, subtype=subtype)
    whole, wave = load_audio(path), Waveform(path)
    S = len(whole)
    assert len(wave) == S and wave.shape == (S,)
    spans = [(0, 1), (0, S), (S - 1, S), (S - 7, S + 5), (3, 4), (16_000 - 1, 16_000 + 1)]
    spans += [tuple(sorted(rng.integers(0, S + 1, 2))) for _ in range(10)]
    for a, b in spans:
        np.testing.assert_array_equal(wave[a:b], whole[a:b])
    np.testing.assert_array_equal(np.asarray(wave), whole)
    np.testing.assert_array_equal(np.concatenate(list(wave.blocks(999))), whole)


def test_open_audio_checks_the_samples_as_load_audio(tmp_path):
    import soundfile as sf

    from talkmesh.audio.waveform import Waveform, open_audio

    x = np.zeros(1600, np.float32)
    sf.write(tmp_path / "ok.flac", x, 16_000)
    assert isinstance(open_audio(tmp_path / "ok.flac"), Waveform)
    x[700] = np.nan
    sf.write(tmp_path / "nan.wav", x, 16_000, subtype="FLOAT")
    with pytest.raises(TalkmeshError, match="1 NaN or infinite"):
        open_audio(tmp_path / "nan.wav")
    with pytest.raises(TalkmeshError, match="not found"):
        open_audio(tmp_path / "gone.wav")


def test_whisper_features_of_a_waveform_equal_the_tensors(tmp_path):
    import soundfile as sf

    from talkmesh.audio.waveform import Waveform

    enc = tiny_whisper(window=7)
    audio = (np.random.default_rng(0).standard_normal(20_777) * 0.1).astype(np.float32)
    sf.write(tmp_path / "a.wav", audio, 16_000, subtype="FLOAT")
    with torch.inference_mode():
        whole = FrameFeatures(enc, torch.from_numpy(audio)[None], 41)
        read = FrameFeatures(enc, Waveform(tmp_path / "a.wav"), 41)
        for a in range(0, 41, 6):
            torch.testing.assert_close(read(a, min(a + 6, 41)), whole(a, min(a + 6, 41)))


def test_animate_blocks_reads_the_file_a_slice_at_a_time(tmp_path, tiny_codetalker):
    """A file's frames and .npz (its audio member too) are those of its waveform loaded whole;
    the blocks hold a Waveform, not the samples."""
    import soundfile as sf

    from talkmesh.audio.loading import load_audio
    from talkmesh.audio.waveform import Waveform
    from talkmesh.face.assets import load_head

    path = tmp_path / "speech44.wav"  # 44.1 kHz stereo: resampled and mixed down as it is read
    speech = load_audio(SPEECH, 44_100)
    sf.write(path, np.stack([speech, 0.5 * speech], 1), 44_100)
    head = load_head()
    model = tiny_codetalker(causal=True, attention_window=7)
    model = CodeTalker(replace(model.cfg, vq=replace(model.cfg.vq, num_vertices=head.num_vertices)))
    learned = save_model(model.eval(), tmp_path / "m.safetensors")
    for m in ("procedural", str(learned)):
        read = animate_blocks(path, model=m, block=7)
        assert isinstance(read.audio, Waveform)
        whole = animate_blocks(load_audio(path), model=m, block=7)
        save_blocks(read, [tmp_path / "read.npz"], overwrite=True)
        save_blocks(whole, [tmp_path / "whole.npz"], overwrite=True)
        a, b = zipfile.ZipFile(tmp_path / "read.npz"), zipfile.ZipFile(tmp_path / "whole.npz")
        assert a.namelist() == b.namelist()
        for name in a.namelist():
            assert a.read(name) == b.read(name), (m, name)


def test_python_peak_memory_does_not_grow_with_the_audio(tmp_path):
    """tracemalloc's peak (numpy's arrays included) of animating a file into an .npz with small
    blocks: 60 s of audio peak within 1 MB of 20 s (the waveform alone would be 2.6 MB more)."""
    import tracemalloc

    import soundfile as sf

    from talkmesh.audio.loading import load_audio
    from talkmesh.audio.phonemes import Phone

    speech = load_audio(SPEECH)

    def peak(seconds: float) -> float:
        path = tmp_path / f"{seconds:g}.wav"
        sf.write(path, np.resize(speech, int(seconds * 16_000)), 16_000)
        phones = [Phone("AA", 0.0, seconds / 2), Phone("SIL", seconds / 2, seconds)]
        tracemalloc.start()
        try:
            anim = animate_blocks(path, phones=phones, block=16)  # no recogniser: fast
            save_blocks(anim, [tmp_path / "out.npz"], overwrite=True)
            return tracemalloc.get_traced_memory()[1] / 1e6
        finally:
            tracemalloc.stop()

    peak(2)  # what is made once (the head, caches) is not counted below
    short, long = peak(20), peak(60)
    assert long - short < 1.0, (short, long)
