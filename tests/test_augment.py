"""Training-time audio augmentation: each step changes the audio as it claims, the motion targets
follow the timing (speed, silence), and everything is seeded."""

from __future__ import annotations

import numpy as np
import pytest

from talkmesh.config import from_dict
from talkmesh.datasets.reader import Sample
from talkmesh.errors import TalkmeshError
from talkmesh.training import augment as aug
from talkmesh.training.augment import AugmentConfig

pytest.importorskip("audiomentations")
pytest.importorskip("pedalboard")
pytest.importorskip("pyroomacoustics")

SR = 16_000
FPS = 30.0
ALL = AugmentConfig(
    speed_p=1, silence_p=1, reverb_p=1, noise_p=1, band_p=1, resample_p=1, gain_p=1, rooms=2
)


def tone(hz: float, seconds: float = 1.0, amp: float = 0.3) -> np.ndarray:
    return (amp * np.sin(2 * np.pi * hz * np.arange(int(SR * seconds)) / SR)).astype(np.float32)


def peak_hz(x: np.ndarray) -> float:
    spectrum = np.abs(np.fft.rfft(x * np.hanning(len(x))))
    return float(np.fft.rfftfreq(len(x), 1 / SR)[np.argmax(spectrum)])


def band_energy(x: np.ndarray, lo: float, hi: float) -> float:
    spectrum = np.abs(np.fft.rfft(x)) ** 2
    f = np.fft.rfftfreq(len(x), 1 / SR)
    return float(spectrum[(f >= lo) & (f < hi)].sum())


def rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.asarray(x, np.float64) ** 2)))


def sample(frames: int = 30, vertices: int = 5) -> Sample:
    """Vertices whose x coordinate is the frame index (a clock), template all zeros."""
    v = np.zeros((frames, vertices, 3), np.float32)
    v[..., 0] = np.arange(frames, dtype=np.float32)[:, None]
    audio = tone(440, frames / FPS)
    return Sample("s", "a", "s1", audio, v, np.zeros((vertices, 3), np.float32), 0)


def test_speed_perturbation_retimes_audio_and_motion_together():
    s = sample(60)
    audio, v = aug.speed_perturb(s.audio, s.vertices, 1.1, FPS)
    assert len(v) == round(60 / 1.1) and len(audio) == round(len(v) * SR / FPS)
    assert peak_hz(audio) == pytest.approx(440 * 1.1, abs=3)  # tempo and pitch together
    # frame j now shows the motion of time j * 1.1: the clock runs 1.1 x faster
    np.testing.assert_allclose(v[:, 0, 0], np.minimum(np.arange(len(v)) * 1.1, 59), atol=1e-4)
    slow_audio, slow = aug.speed_perturb(s.audio, s.vertices, 0.9, FPS)
    assert len(slow) == round(60 / 0.9) and peak_hz(slow_audio) == pytest.approx(396, abs=3)


def test_inserted_silence_is_silent_with_closed_mouth_targets():
    s = sample(30)
    s = s._replace(vertices=s.vertices + 1.0)  # never the template, to tell them apart
    audio, v = aug.insert_silence(s.audio, s.vertices, s.template, 10, 15, FPS)
    assert len(v) == 45 and len(audio) == round(45 * SR / FPS)
    a0, a1 = round(10 * SR / FPS), round(25 * SR / FPS)
    assert not audio[a0:a1].any() and rms(audio[:a0]) > 0.1 and rms(audio[a1:]) > 0.1
    np.testing.assert_array_equal(v[:10], s.vertices[:10])
    np.testing.assert_array_equal(v[25:], s.vertices[10:])
    np.testing.assert_array_equal(v[13:22], 0.0)  # the mouth closed: the neutral template
    steps = np.abs(np.diff(v[9:26, 0, 0]))
    assert steps.max() < 0.5 * np.abs(v[9, 0, 0] - 0.0)  # ramped, no jump to the template
    lead_audio, lead = aug.insert_silence(s.audio, s.vertices, s.template, 0, 6, FPS)
    np.testing.assert_array_equal(lead[:4], 0.0)
    assert not lead_audio[: round(6 * SR / FPS)].any()
    _, trail = aug.insert_silence(s.audio, s.vertices, s.template, 30, 6, FPS)
    np.testing.assert_array_equal(trail[-4:], 0.0)


@pytest.mark.parametrize("ramp_s,frames", [(0.0, 0), (0.06, 2), (0.1, 3)])
def test_the_silence_ramps_last_as_long_as_the_recipe_says(ramp_s, frames, monkeypatch):
    """Each ramp lies inside the silence: a model learns to open its mouth that far ahead of
    speech, so the ramp is the recipe's (``data.augment.silence_ramp_s``)."""
    s = sample(30)
    s = s._replace(vertices=s.vertices + 1.0)
    _, v = aug.insert_silence(s.audio, s.vertices, s.template, 10, 15, FPS, ramp_s)
    gap = v[10:25, 0, 0]
    moving = gap != 0.0  # the template is 0: frames off it are ramps
    assert moving[:frames].all() and moving[15 - frames :].all()
    assert not moving[frames : 15 - frames].any()
    seen = []
    real = aug.insert_silence
    monkeypatch.setattr(aug, "insert_silence", lambda *a: seen.append(a[-1]) or real(*a))
    cfg = AugmentConfig(silence_p=1.0, silence_ramp_s=ramp_s, silence_seconds=(0.5, 0.5))
    out = aug.augment(s, cfg, np.random.default_rng(1), FPS)
    assert len(out.vertices) == 45 and seen == [ramp_s]  # the recipe's ramp reaches the silence


def test_reverb_adds_a_decaying_tail_in_sync():
    rirs = aug.room_impulse_responses(2, (0.4, 0.6), 0)
    assert len(rirs) == 2 and all(np.argmax(np.abs(r)) < 16 for r in rirs)  # direct path first
    click = np.zeros(SR // 2, np.float32)
    click[1000] = 1.0
    wet = aug.reverberate(click, rirs[0])
    assert len(wet) == len(click) and np.argmax(np.abs(wet)) - 1000 < 16
    assert rms(wet[1000 + 800 : 1000 + 3200]) > 1e-3  # 50-200 ms later the room still rings
    assert aug.room_impulse_responses(2, (0.4, 0.6), 0) is rirs  # the bank is built once


def test_noise_fills_the_pauses_at_the_requested_snr():
    speech = np.concatenate([tone(300), np.zeros(SR, np.float32)])
    noisy = aug.add_noise(speech, 10.0, -3.0, seed=1)
    noise = noisy - speech
    assert rms(noisy[SR:]) > 0  # the pause is no longer digital silence
    assert 20 * np.log10(rms(speech) / rms(noise)) == pytest.approx(10.0, abs=0.5)
    np.testing.assert_array_equal(noisy, aug.add_noise(speech, 10.0, -3.0, seed=1))
    state = np.random.get_state()[1].copy()
    aug.add_noise(speech, 10.0, -3.0, seed=2)
    np.testing.assert_array_equal(np.random.get_state()[1], state)  # global RNG untouched


def test_telephone_and_band_limits_remove_what_they_claim():
    x = tone(1000) + tone(6000) + tone(100)
    phone = aug.telephone(x)
    assert len(phone) == len(x)
    assert band_energy(phone, 5500, 6500) < 1e-3 * band_energy(x, 5500, 6500)
    assert band_energy(phone, 900, 1100) > 0.1 * band_energy(x, 900, 1100)
    low = aug.band_limit(x, "low", 2000.0)
    assert band_energy(low, 5500, 6500) < 0.05 * band_energy(x, 5500, 6500)
    high = aug.band_limit(x, "high", 500.0)
    assert band_energy(high, 50, 150) < 0.05 * band_energy(x, 50, 150)


def test_resample_round_trip_limits_the_band_at_low_rates_only():
    x = tone(1000) + tone(6000)
    low = aug.resample_round_trip(x, 8000)
    assert len(low) == len(x)
    assert band_energy(low, 5500, 6500) < 0.01 * band_energy(x, 5500, 6500)
    high = aug.resample_round_trip(x, 48000)
    assert band_energy(high, 5500, 6500) > 0.5 * band_energy(x, 5500, 6500)


def test_gain_changes_the_level_and_clips():
    x = tone(440, amp=0.05)
    assert rms(aug.apply_gain(x, 20.0)) == pytest.approx(10 * rms(x), rel=1e-4)
    assert rms(aug.apply_gain(x, -20.0)) == pytest.approx(0.1 * rms(x), rel=1e-4)
    assert np.abs(aug.apply_gain(tone(440, amp=0.5), 20.0)).max() == 1.0


def test_augment_is_seeded_keeps_audio_and_motion_aligned_and_can_be_off():
    s = sample(60)
    a = aug.augment(s, ALL, np.random.default_rng(3), FPS)
    b = aug.augment(s, ALL, np.random.default_rng(3), FPS)
    np.testing.assert_array_equal(a.audio, b.audio)
    np.testing.assert_array_equal(a.vertices, b.vertices)
    c = aug.augment(s, ALL, np.random.default_rng(4), FPS)
    assert a.audio.shape != c.audio.shape or not np.array_equal(a.audio, c.audio)
    for seed in range(6):
        out = aug.augment(s, ALL, np.random.default_rng(seed), FPS)
        assert abs(len(out.audio) - len(out.vertices) * SR / FPS) <= 1
        assert out.audio.dtype == np.float32 and np.abs(out.audio).max() <= 1.0
    assert aug.augment(s, AugmentConfig(), np.random.default_rng(0), FPS) is s


def test_config_checks_its_values():
    cfg = from_dict(AugmentConfig, {"noise_p": 0.5, "snr_db": [5, 20]}, "data.augment")
    assert cfg.enabled and cfg.snr_db == (5.0, 20.0)
    assert not AugmentConfig().enabled
    with pytest.raises((TalkmeshError, ValueError), match="noise_p"):
        from_dict(AugmentConfig, {"noise_p": 1.5}, "data.augment")
    with pytest.raises((TalkmeshError, ValueError), match="snr_db"):
        from_dict(AugmentConfig, {"snr_db": [20, 5]}, "data.augment")
    with pytest.raises(TalkmeshError, match="unknown config key"):
        from_dict(AugmentConfig, {"noize_p": 0.5}, "data.augment")
    with pytest.raises((TalkmeshError, ValueError), match="silence_ramp_s"):
        from_dict(AugmentConfig, {"silence_ramp_s": -0.1}, "data.augment")


def test_finetune_continues_a_release_on_augmented_audio(tiny_corpus, tmp_path):
    """``task: codetalker-finetune``: the release's VQ-VAE and speech statistics stay, the rest
    learns from augmented crops, and a release of the same shape comes out."""
    pytest.importorskip("lightning")
    import torch

    from talkmesh.datasets.reader import open_dataset
    from talkmesh.models.codetalker.model import CodeTalker
    from talkmesh.models.release import load_model, save_model
    from talkmesh.training.trainer import load_recipe, train

    spec = open_dataset("synth", tiny_corpus, "train").spec
    torch.manual_seed(0)
    base = CodeTalker(CodeTalker.tiny_config(spec.num_vertices, tuple(spec.train_subjects)))
    save_model(base, tmp_path / "base.safetensors")
    recipe_file = tmp_path / "ft.yaml"
    recipe_file.write_text(
        "task: codetalker-finetune\n"
        f"init: {tmp_path / 'base.safetensors'}\n"
        f"data: {{kind: synth, root: {tiny_corpus}, batch_size: 1, max_seconds: 1.0, val_split: ''}}\n"
        "train: {lr: 1.0e-3, epochs: 1, max_steps: 2, accelerator: cpu, out_dir: "
        f"{tmp_path / 'run'}}}\n"
    )
    augmented = [f"data.augment.{k}_p=1" for k in ("speed", "silence", "noise", "gain")]
    out = train(load_recipe(recipe_file, augmented), progress=False)
    tuned = load_model(out)
    before, after = base.state_dict(), tuned.state_dict()
    assert before.keys() == after.keys()
    buffers = set(dict(base.named_buffers())) & set(before)
    kept = {k for k in before if k.startswith("vqvae.")} | buffers
    for k in kept:  # the motion codebook and the speech normalisation are the release's
        assert torch.equal(before[k], after[k]), k
    assert any(not torch.equal(before[k], after[k]) for k in before if k.startswith("blocks."))
    with pytest.raises(TalkmeshError, match="may only say head_pairs"):
        train(load_recipe(recipe_file, ["model.preset=small", f"train.out_dir={tmp_path}/b"]))
    other = CodeTalker(CodeTalker.tiny_config(spec.num_vertices, ("x", "y")))
    save_model(other, tmp_path / "other.safetensors")
    with pytest.raises(TalkmeshError, match="trained on the speakers x, y"):
        train(
            load_recipe(
                recipe_file, [f"init={tmp_path}/other.safetensors", f"train.out_dir={tmp_path}/c"]
            )
        )


def test_finetune_adds_the_corpus_new_speakers_at_the_mean_style(tiny_corpus, tmp_path):
    """A release continued on a corpus with more training speakers keeps the styles it learned
    and starts each new speaker at their mean (the style an unseen speaker gets)."""
    pytest.importorskip("lightning")
    import torch

    from talkmesh.datasets.reader import open_dataset
    from talkmesh.models.codetalker.model import CodeTalker
    from talkmesh.models.release import load_model, save_model
    from talkmesh.training.codetalker import with_styles
    from talkmesh.training.trainer import load_recipe, train

    subjects = tuple(open_dataset("synth", tiny_corpus, "train").spec.train_subjects)
    assert len(subjects) >= 2
    torch.manual_seed(1)
    base = CodeTalker(CodeTalker.tiny_config(8, subjects[:1] + ("gone",)))
    stray = CodeTalker(CodeTalker.tiny_config(8, ("p",)))
    stray.register_buffer("stray", torch.zeros(1))  # weights its config does not know
    with pytest.raises(TalkmeshError, match="cannot add speakers"):
        with_styles(stray, ("p", "q"))
    grown = with_styles(base, ("new", subjects[0], "gone"))
    old = base.style.weight.detach()
    assert torch.equal(grown.style.weight[1], old[0]) and torch.equal(grown.style.weight[2], old[1])
    assert torch.allclose(grown.style.weight[0], old.mean(0))
    same = {k: v for k, v in grown.state_dict().items() if k != "style.weight"}
    assert all(torch.equal(v, base.state_dict()[k]) for k, v in same.items())

    spec = open_dataset("synth", tiny_corpus, "train").spec
    torch.manual_seed(0)
    first = CodeTalker(CodeTalker.tiny_config(spec.num_vertices, subjects[:1]))
    save_model(first, tmp_path / "first.safetensors")
    recipe_file = tmp_path / "more.yaml"
    recipe_file.write_text(
        "task: codetalker-finetune\n"
        f"init: {tmp_path / 'first.safetensors'}\n"
        f"data: {{kind: synth, root: {tiny_corpus}, batch_size: 1, max_seconds: 1.0, val_split: ''}}\n"
        f"train: {{lr: 1.0e-3, epochs: 1, max_steps: 1, accelerator: cpu, out_dir: {tmp_path}}}\n"
    )
    tuned = load_model(train(load_recipe(recipe_file), progress=False))
    assert tuned.styles == subjects


def test_the_finetune_recipe_augments_and_continues_the_bundled_model():
    pytest.importorskip("yaml")
    from pathlib import Path

    from talkmesh.training.trainer import _init_path, load_recipe

    recipe = load_recipe(Path(__file__).parents[1] / "configs" / "codetalker_finetune_real.yaml")
    assert recipe.task == "codetalker-finetune" and recipe.data.augment.enabled
    assert _init_path(recipe.init).name == "codetalker-synth.safetensors"
    with pytest.raises(TalkmeshError, match="init checkpoint not found"):
        _init_path("no-such-model")
