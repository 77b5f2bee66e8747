"""FaceFormer invariants on tiny configurations, and one end-to-end training run."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import pytest
import torch

from talkmesh.config import from_dict, to_dict
from talkmesh.errors import TalkmeshError
from talkmesh.models.faceformer.model import (
    FaceFormer,
    FaceFormerConfig,
    biwi_config,
    decoder_bias,
    small_synth_config,
    vocaset_config,
)
from talkmesh.models.release import load_model, save_model
from talkmesh.models.speech import SpeechEncoderConfig

SR = 16_000
FPS = 30
V = 20
CONFIGS = Path(__file__).resolve().parents[1] / "configs"


def tiny(**overrides) -> FaceFormer:
    torch.manual_seed(0)
    cfg = FaceFormerConfig(
        num_vertices=V,
        styles=("a", "b"),
        d_model=32,
        heads=2,
        ff=64,
        layers=2,
        period=5,
        speech=SpeechEncoderConfig(kind="mel", dim=16),
    )
    model = FaceFormer(replace(cfg, **overrides))
    # the zero-initialised motion decoder would make every frame the template
    for p in model.out.parameters():
        torch.nn.init.normal_(p, std=0.5)
    model.scale.fill_(0.01)
    return model.eval()


def clip(frames: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """(1, S) audio and (1, T, V, 3) vertices of ``frames`` motion frames."""
    g = torch.Generator().manual_seed(seed)
    audio = torch.randn(1, frames * SR // FPS, generator=g)
    return audio, torch.randn(1, frames, V, 3, generator=g) * 0.01


def test_config_round_trips_and_validates():
    for cfg in (tiny().cfg, vocaset_config(), biwi_config(), small_synth_config(("a",), 7)):
        data = json.loads(json.dumps(to_dict(cfg)))
        assert from_dict(FaceFormerConfig, data) == cfg
    paper = vocaset_config()
    assert (paper.d_model, paper.period, paper.layers, paper.heads, paper.ff) == (64, 30, 1, 4, 128)
    assert paper.speech.source == "facebook/wav2vec2-base-960h"
    with pytest.raises(ValueError, match="divisible"):
        replace(paper, heads=3)
    with pytest.raises(ValueError, match="frame_rate"):  # 25 fps x 2 tokens needs 50 Hz
        replace(biwi_config(), speech=SpeechEncoderConfig(kind="mel"))
    with pytest.raises(ValueError, match="styles"):
        replace(paper, styles=())


def test_save_load_gives_identical_output(tmp_path):
    model = tiny()
    path = save_model(model, tmp_path / "m.safetensors")
    again = load_model(path)
    assert again.family == "faceformer" and again.styles == ("a", "b")
    assert again.num_vertices == V and again.motion_fps == FPS
    assert float(again.scale) == pytest.approx(0.01)
    audio, _ = clip(8)
    templ = torch.randn(1, V, 3)
    style = torch.tensor([1])
    out = model.generate(audio, templ, styles=style)
    assert torch.equal(again.generate(audio, templ, styles=style), out)
    assert out.shape == (1, 8, V, 3) and out.std(dim=1).max() > 0


def test_padded_batch_equals_single_samples():
    model = tiny()
    (a_audio, a_v), (b_audio, b_v) = clip(7, 1), clip(11, 2)
    audio = torch.zeros(2, b_audio.shape[1])
    audio[0, : a_audio.shape[1]], audio[1] = a_audio[0], b_audio[0]
    verts = torch.zeros(2, 11, V, 3)
    verts[0, :7], verts[1] = a_v[0], b_v[0]
    mask = torch.zeros(2, 11, dtype=torch.bool)
    mask[0, :7], mask[1] = True, True
    lengths = torch.tensor([a_audio.shape[1], b_audio.shape[1]])
    templ = torch.randn(2, V, 3)
    styles = torch.tensor([0, 1])
    with torch.no_grad():
        batch = model(audio, lengths, verts + templ[:, None], templ, styles, mask)
        alone_a = model(a_audio, None, a_v + templ[:1, None], templ[:1], styles[:1])
        alone_b = model(b_audio, None, b_v + templ[1:, None], templ[1:], styles[1:])
    torch.testing.assert_close(batch.motion[0, :7], alone_a.motion[0], atol=1e-5, rtol=1e-4)
    torch.testing.assert_close(batch.motion[1], alone_b.motion[0], atol=1e-5, rtol=1e-4)
    # the loss of the padded batch counts valid frames only
    pooled = (alone_a.loss * 7 + alone_b.loss * 11) / 18
    torch.testing.assert_close(batch.loss, pooled, atol=1e-6, rtol=1e-4)
    gen = model.generate(audio, templ, styles=styles, audio_lengths=lengths, num_frames=11)
    gen_a = model.generate(a_audio, templ[:1], styles=styles[:1], num_frames=7)
    gen_b = model.generate(b_audio, templ[1:], styles=styles[1:], num_frames=11)
    torch.testing.assert_close(gen[0, :7], gen_a[0], atol=1e-5, rtol=1e-4)
    torch.testing.assert_close(gen[1], gen_b[0], atol=1e-5, rtol=1e-4)


@pytest.mark.parametrize("mode", ["fast", "naive"])
def test_generation_is_causal(mode):
    model = tiny()
    audio, _ = clip(20)
    t, lookahead = 9, 4  # the mel encoder hears 100 ms (3 frames) ahead; one frame of margin
    changed = audio.clone()
    start = (t + 1 + lookahead) * SR // FPS
    changed[:, start:] = torch.randn_like(changed[:, start:])
    templ, style = torch.zeros(1, V, 3), torch.tensor([0])
    a = model.generate(audio, templ, styles=style, mode=mode)
    b = model.generate(changed, templ, styles=style, mode=mode)
    assert torch.equal(a[:, : t + 1], b[:, : t + 1])
    assert not torch.allclose(a[:, t + 1 + lookahead :], b[:, t + 1 + lookahead :])


@pytest.mark.parametrize("window", [600, 4])
def test_fast_generation_equals_the_naive_loop(window):
    model = tiny(attention_window=window)  # window 4: the cache drops frames, the naive bias too
    audio = torch.cat([clip(23, 1)[0], clip(23, 2)[0]])
    templ = torch.randn(2, V, 3)
    weights = torch.tensor([[0.3, 0.7], [1.0, 0.0]])
    fast = model.generate(audio, templ, style_weights=weights, mode="fast")
    naive = model.generate(audio, templ, style_weights=weights, mode="naive")
    assert fast.shape == (2, 23, V, 3)
    torch.testing.assert_close(fast, naive, atol=1e-5, rtol=1e-5)
    assert not torch.allclose(fast[0], fast[1])


def test_teacher_forced_forward_on_its_own_output_equals_generation():
    model = tiny(attention_window=6)
    audio, _ = clip(14)
    templ = torch.randn(1, V, 3)
    style = torch.tensor([1])
    gen = model.generate(audio, templ, styles=style)
    with torch.no_grad():
        forced = model(audio, None, gen, templ, style)
    torch.testing.assert_close(forced.motion.view_as(gen) + templ[:, None], gen, atol=1e-5, rtol=0)
    assert forced.loss < 1e-8


def test_decoder_bias_is_periodic_causal_and_windowed():
    b = decoder_bias(2, 6, 6, period=2, window=3)
    assert torch.isinf(b[0, 0, 1]) and b[0, 1, 0] == 0 and b[0, 2, 0] == -0.25
    assert b[1, 2, 0] == -1 / 16
    assert torch.isinf(b[0, 5, 2]) and torch.isfinite(b[0, 5, 3])  # only the last 3 keys


def test_styles_and_unseen_speakers():
    model = tiny()
    audio, _ = clip(6)
    templ = torch.zeros(1, V, 3)
    pure = model.generate(audio, templ, styles=torch.tensor([0]))
    one_hot = model.generate(audio, templ, style_weights=torch.tensor([[1.0, 0.0]]))
    torch.testing.assert_close(pure, one_hot)
    mean = model.generate(audio, templ, style_weights=torch.tensor([[0.5, 0.5]]))
    assert not torch.allclose(mean, pure)
    with pytest.raises(TalkmeshError, match="unseen speaker needs style weights"):
        model.generate(audio, templ)
    with pytest.raises(TalkmeshError, match="unseen speaker"):
        model.generate(audio, templ, styles=torch.tensor([-1]))
    with pytest.raises(TalkmeshError, match=r"style_weights must be \(batch, 2\)"):
        model.generate(audio, templ, style_weights=torch.ones(1, 3))
    # in training, a speaker outside the training set (-1) gets the mean style
    with torch.no_grad():
        unseen = model(audio, None, mean, templ, torch.tensor([-1]))
    torch.testing.assert_close(unseen.motion.view_as(mean), mean, atol=1e-5, rtol=0)


def test_bad_inputs_raise_clear_errors():
    model = tiny()
    audio, verts = clip(5)
    style = torch.tensor([0])
    with pytest.raises(TalkmeshError, match="20-vertex meshes, got shape \\(1, 19, 3\\)"):
        model.generate(audio, torch.zeros(1, 19, 3), styles=style)
    with pytest.raises(TalkmeshError, match="20-vertex"):
        model(audio, None, verts[:, :, :19], torch.zeros(1, 19, 3), style)
    with pytest.raises(TalkmeshError, match="vertices must be"):
        model(audio, None, verts[:, :, :19], torch.zeros(1, V, 3), style)
    with pytest.raises(TalkmeshError, match="audio must be"):
        model.generate(audio[0], torch.zeros(1, V, 3), styles=style)
    with pytest.raises(TalkmeshError, match="unknown generation mode"):
        model.generate(audio, torch.zeros(1, V, 3), styles=style, mode="slow")


def test_a_few_steps_lower_the_loss_and_self_feedback_acts_in_training_only():
    model = tiny(self_feedback=0.5, dropout=0.0)
    audio, verts = clip(12)
    templ = torch.zeros(1, V, 3)
    verts = verts + torch.linspace(0, 0.05, 12)[None, :, None, None]  # a slow drift to learn
    args = (audio, None, verts, templ, torch.tensor([0]))
    with torch.no_grad():
        plain = model(*args).loss
        torch.testing.assert_close(model(*args).loss, plain)  # eval: no self-feedback
        model.train()
        torch.manual_seed(1)
        assert not torch.allclose(model(*args).loss, plain)  # its own frames are fed back
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)
    losses = []
    for _ in range(25):
        opt.zero_grad()
        loss = model(*args).loss
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < 0.5 * losses[0]
    with pytest.raises(ValueError, match="self_feedback"):
        replace(model.cfg, self_feedback=1.5)


def own_batch(audio, verts, templ) -> object:
    from talkmesh.training.trainer import TorchBatch

    B, T = verts.shape[:2]
    lengths = torch.full((B,), audio.shape[1])
    return TorchBatch(
        ["x"] * B,
        audio,
        lengths,
        verts,
        templ,
        torch.ones(B, T, dtype=torch.bool),
        torch.zeros(B, dtype=torch.long),
    )


def test_training_on_own_predictions_is_the_generation_loop_and_learns():
    from talkmesh.training.faceformer import FACEFORMER, own_predictions

    model = tiny(teacher_forcing=False, dropout=0.0)
    audio, verts = clip(12)
    templ = torch.randn(1, V, 3) * 0.1
    verts = templ[:, None] + torch.linspace(0, 0.05, 12)[None, :, None, None]  # a drift to learn
    batch = own_batch(audio, verts, templ)
    with torch.no_grad():
        pred, loss = own_predictions(model, batch)
    # without dropout, the training loop's prediction is what generation feeds back and returns
    gen = model.generate(audio, templ, styles=torch.tensor([0]), num_frames=12, mode="naive")
    torch.testing.assert_close(pred.view(1, 12, V, 3) * model.scale + templ[:, None], gen)
    teacher = model(audio, None, verts, templ, torch.tensor([0])).loss
    assert not torch.allclose(loss, teacher)  # not the teacher-forced loss
    model.train()
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)
    losses = []
    for _ in range(25):
        opt.zero_grad()
        step_loss = FACEFORMER.step(model, batch).loss  # the task's step runs the own-loop
        step_loss.backward()
        opt.step()
        losses.append(step_loss.item())
    assert losses[-1] < 0.5 * losses[0]
    with pytest.raises(ValueError, match="teacher_forcing False"):
        replace(model.cfg, self_feedback=0.5)


def test_own_predictions_send_gradients_through_the_fed_back_frames():
    from talkmesh.training.faceformer import own_predictions

    model = tiny(teacher_forcing=False, dropout=0.0)
    audio, verts = clip(6)
    templ = torch.zeros(1, V, 3)
    pred, _ = own_predictions(model, own_batch(audio, verts, templ))
    # teacher forced, d(last frame)/d(motion decoder bias) is the identity (a sum of ones); here
    # the bias also reaches the last frame through every frame fed back before it
    (grad,) = torch.autograd.grad(pred[0, -1].sum(), model.out.bias)
    assert not torch.allclose(grad, torch.ones_like(grad))
    tf = model(audio, None, verts, templ, torch.tensor([0])).motion
    (grad,) = torch.autograd.grad(tf[0, -1].sum(), model.out.bias)
    torch.testing.assert_close(grad, torch.ones_like(grad) * model.scale)


@pytest.mark.parametrize("name", ["faceformer_synth", "faceformer_vocaset"])
def test_recipes_map_onto_the_config(name):
    from talkmesh.training.faceformer import build_config
    from talkmesh.training.trainer import DatasetInfo, load_recipe

    recipe = load_recipe(CONFIGS / f"{name}.yaml", ["train.seed=3"])
    assert recipe.task == "faceformer" and recipe.train.seed == 3
    info = DatasetInfo(num_vertices=100, motion_fps=25.0, train_subjects=("x", "y", "z"))
    cfg = build_config(recipe.model, info)
    assert cfg.num_vertices == 100 and cfg.styles == ("x", "y", "z")
    assert cfg.motion_fps == 25.0 and cfg.speech.frame_rate == 25.0
    if name == "faceformer_vocaset":
        assert (cfg.d_model, cfg.period, cfg.layers) == (64, 30, 1)
        assert cfg.speech.kind == "wav2vec2"
        assert cfg.speech.source == "facebook/wav2vec2-base-960h"
    else:
        assert cfg.speech.kind == "whisper" and cfg.self_feedback == 0.5
    with pytest.raises(TalkmeshError, match="model.preset"):
        build_config({"preset": "huge"}, info)
    with pytest.raises(TalkmeshError, match="unknown config key model.widht"):
        build_config({"widht": 3}, info)


def test_train_one_epoch_end_to_end_and_release(tmp_path):
    from talkmesh.datasets.synth import make_corpus
    from talkmesh.training.trainer import load_recipe, train

    corpus = tmp_path / "corpus"
    make_corpus(corpus, subjects=3, sentences=2, seed=3, workers=1, progress=False)
    out = tmp_path / "run"
    recipe = load_recipe(
        CONFIGS / "faceformer_synth.yaml",
        [
            f"data.root={corpus}",
            f"train.out_dir={out}",
            "train.epochs=1",
            "data.batch_size=2",
            "data.max_seconds=1.0",
            "train.accelerator=cpu",
            "model.speech.kind=mel",
            "model.speech.source=null",
            "model.speech.dim=16",
            "model.d_model=16",
            "model.ff=32",
            "model.layers=1",
            "model.heads=2",
        ],
    )
    path = train(recipe, progress=False)
    assert path == out / "model.safetensors" and path.is_file()
    model = load_model(path)
    assert model.family == "faceformer" and model.styles == ("Synth_01_ada", "Synth_02_bo")
    assert model.num_vertices == 4766 and model.motion_fps == 30.0
    assert float(model.scale) != 1.0  # prepare fitted the motion scale...
    fresh = FaceFormer(model.cfg)  # ...and the mel statistics
    assert not torch.allclose(model.speech.encoder.mel_mean, fresh.speech.encoder.mel_mean)
    audio = torch.randn(1, SR // 2)
    weights = torch.full((1, 2), 0.5)
    verts = model.generate(audio, torch.zeros(1, 4766, 3), style_weights=weights)
    assert verts.shape == (1, 15, 4766, 3) and torch.isfinite(verts).all()
