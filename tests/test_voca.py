"""VOCA invariants on tiny configurations."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from fixtures import TINY_WAV2VEC2, make_dataset

from talkmesh.config import from_dict, to_dict
from talkmesh.datasets.reader import DatasetSpec
from talkmesh.errors import TalkmeshError
from talkmesh.models.release import load_model, save_model
from talkmesh.models.speech import SpeechEncoderConfig
from talkmesh.models.voca.model import VOCA, VOCAConfig, principal_directions, voca_loss

SR = 16_000
FPS = 30
V = 20
CONFIGS = Path(__file__).resolve().parents[1] / "configs"


def speech_config(kind: str = "mel") -> SpeechEncoderConfig:
    return SpeechEncoderConfig(
        kind=kind, dim=16, hf_config=TINY_WAV2VEC2 if kind == "wav2vec2" else {}
    )


def tiny_config(**overrides) -> VOCAConfig:
    base = dict(
        num_vertices=V,
        styles=("a", "b"),
        speech=speech_config(),
        conv_channels=(8, 8, 16, 16),
        hidden=16,
        latent=6,
    )
    return VOCAConfig(**{**base, **overrides})


def tiny(**overrides) -> VOCA:
    torch.manual_seed(0)
    model = VOCA(tiny_config(**overrides))
    g = torch.Generator().manual_seed(1)
    model.set_basis(torch.randn(80, V * 3, generator=g))  # a decoder that moves the mesh
    return model.eval()


def clip(frames: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """(1, S) audio and (1, T, V, 3) vertices of ``frames`` motion frames."""
    g = torch.Generator().manual_seed(seed)
    audio = torch.randn(1, frames * SR // FPS, generator=g)
    return audio, torch.randn(1, frames, V, 3, generator=g) * 0.01


def test_config_round_trip_and_validation():
    cfg = tiny_config(window_before=4, window_after=12)
    again = from_dict(VOCAConfig, json.loads(json.dumps(to_dict(cfg))))
    assert again == cfg and to_dict(again) == to_dict(cfg)
    assert cfg.speech.frame_rate == FPS * cfg.tokens_per_frame  # derived: 60 Hz windows
    assert cfg.window == 16
    with pytest.raises(TalkmeshError, match="latent"):
        from_dict(VOCAConfig, {**to_dict(cfg), "latent": 0})
    with pytest.raises(TalkmeshError, match="unknown config key"):
        from_dict(VOCAConfig, {**to_dict(cfg), "dropout": 0.1})


@pytest.mark.parametrize("frames", [40, 200])  # fewer frames than coordinates, and more
def test_pca_decoder_reproduces_training_offsets_up_to_the_truncation(frames):
    rng = np.random.default_rng(frames)
    D, L = V * 3, 6
    # a decaying spectrum, so the top components are well separated
    x = rng.standard_normal((frames, D)) @ np.diag(0.5 ** np.arange(D)) @ np.linalg.qr(
        rng.standard_normal((D, D))
    )[0] + rng.standard_normal(D)
    model = VOCA(tiny_config(latent=L))
    model.set_basis(torch.from_numpy(x).float())
    W = model.decoder.weight.detach().double().numpy()  # (D, L)
    b = model.decoder.bias.detach().double().numpy()

    mean = x.mean(0)
    _, s, vt = np.linalg.svd(x - mean, full_matrices=False)
    np.testing.assert_allclose(b, mean, atol=1e-5)
    # columns: the top principal directions, scaled by their standard deviation s / sqrt(N)
    for k in range(L):
        col = W[:, k]
        assert np.linalg.norm(col) == pytest.approx(s[k] / np.sqrt(frames), rel=1e-4)
        assert abs(col @ vt[k]) / np.linalg.norm(col) == pytest.approx(1.0, abs=1e-4)

    # a latent equal to the PCA coefficients (in units of each component's std) decodes to the
    # rank-L reconstruction, whose error is exactly the energy of the dropped components
    z = (x - b) @ W / (W**2).sum(0)
    with torch.no_grad():
        decoded = model.decoder(torch.from_numpy(z).float()).double().numpy()
    rank_l = mean + (x - mean) @ vt[:L].T @ vt[:L]
    np.testing.assert_allclose(decoded, rank_l, atol=1e-4)
    residual = np.linalg.norm(decoded - x)
    assert residual == pytest.approx(np.sqrt((s[L:] ** 2).sum()), rel=1e-3)
    assert residual < 0.05 * np.linalg.norm(x - mean)


def test_pca_of_rank_deficient_motion_leaves_the_extra_components_at_zero():
    x = torch.randn(50, 2, dtype=torch.float64) @ torch.randn(2, V * 3, dtype=torch.float64)
    mean, dirs, s = principal_directions(x, 6)
    assert dirs.shape == (2, V * 3) and len(s) == 2
    torch.testing.assert_close(dirs @ dirs.T, torch.eye(2, dtype=torch.float64))
    model = VOCA(tiny_config())
    model.set_basis(x.float())
    assert model.decoder.weight[:, 2:].abs().max() == 0
    with pytest.raises(TalkmeshError, match="PCA offsets"):
        model.set_basis(torch.zeros(10, 7))


def test_velocity_loss_is_zero_for_the_target_and_positive_otherwise():
    target = torch.randn(2, 6, 12)
    same = voca_loss(target.clone(), target)
    assert same.position == 0 and same.velocity == 0 and same.loss == 0
    shifted = voca_loss(target + 0.3, target)  # a constant error has no velocity error
    assert shifted.position > 0 and shifted.velocity.abs() < 1e-10
    jitter = target.clone()
    jitter[:, 3] += 0.1
    moved = voca_loss(jitter, target, velocity_weight=10.0)
    # frame 3 is wrong by 0.1 in 12 coordinates: twice per sequence in the velocity, once in
    # the position; means over the 2 * 5 pairs and 2 * 6 frames
    assert moved.velocity.item() == pytest.approx(2 * 2 * 12 * 0.01 / 10, rel=1e-4)
    assert moved.position.item() == pytest.approx(2 * 12 * 0.01 / 12, rel=1e-4)
    assert moved.loss.item() == pytest.approx(moved.position.item() + 10 * moved.velocity.item())
    # masked frames do not count
    mask = torch.ones(2, 6, dtype=torch.bool)
    mask[:, 3:] = False
    assert voca_loss(jitter, target, mask).loss == 0


@pytest.mark.parametrize("speech", ["mel", "wav2vec2"])
def test_padded_batch_equals_single_samples(speech):
    model = tiny(speech=speech_config(speech))
    model.set_feature_statistics(torch.randn(40, 16) * 3 + 2)  # padding tokens are not zero-mean
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
        batch = model(audio, lengths, verts, templ, styles, mask)
        alone_a = model(a_audio, None, a_v, templ[:1], styles[:1])
        alone_b = model(b_audio, None, b_v, templ[1:], styles[1:])
        no_lengths = model(audio, None, verts, templ, styles, mask)  # lengths from the mask
    torch.testing.assert_close(no_lengths.vertices, batch.vertices)
    torch.testing.assert_close(batch.vertices[0, :7], alone_a.vertices[0], atol=1e-5, rtol=1e-4)
    torch.testing.assert_close(batch.vertices[1], alone_b.vertices[0], atol=1e-5, rtol=1e-4)

    gen = model.generate(audio, templ, styles=styles, audio_lengths=lengths)
    gen_a = model.generate(a_audio, templ[:1], styles=styles[:1])
    gen_b = model.generate(b_audio, templ[1:], styles=styles[1:])
    assert gen.shape == (2, 11, V, 3) and gen_a.shape == (1, 7, V, 3)
    torch.testing.assert_close(gen[0, :7], gen_a[0], atol=1e-5, rtol=1e-4)
    torch.testing.assert_close(gen[1], gen_b[0], atol=1e-5, rtol=1e-4)
    torch.testing.assert_close(gen[0, 7:], templ[0].expand(4, V, 3))  # rests after its audio
    torch.testing.assert_close(gen_a[0], alone_a.vertices[0], atol=1e-5, rtol=1e-4)
    assert gen_a.std(dim=1).max() > 0  # frames differ: the speech drives them


def test_generate_is_deterministic_and_styles_mix():
    model = tiny()
    audio, _ = clip(9)
    templ = torch.zeros(1, V, 3)
    one = model.generate(audio, templ, styles=torch.tensor([0]), seed=0)
    torch.testing.assert_close(one, model.generate(audio, templ, styles=torch.tensor([0]), seed=5))
    torch.testing.assert_close(
        one, model.generate(audio, templ, style_weights=torch.tensor([[1.0, 0.0]]))
    )
    other = model.generate(audio, templ, styles=torch.tensor([1]))
    assert not torch.allclose(one, other)  # the speaker one-hot changes the output
    with pytest.raises(TalkmeshError, match="unseen speaker"):
        model.generate(audio, templ, styles=torch.tensor([-1]))
    with pytest.raises(TalkmeshError, match="style weights must be"):
        model.generate(audio, templ, style_weights=torch.ones(1, 3))


def test_frames_depend_only_on_their_speech_window():
    model = tiny()
    audio, _ = clip(60)
    templ = torch.zeros(1, V, 3)
    changed = audio.clone()
    changed[:, int(1.5 * SR) :] = torch.randn_like(changed[:, int(1.5 * SR) :])
    a = model.generate(audio, templ, styles=torch.tensor([0]))
    b = model.generate(changed, templ, styles=torch.tensor([0]))
    # frame t reads tokens up to t/30 s + 8/60 s, whose mel features see 100 ms (+ half an FFT
    # window) further: frames before ~1.2 s cannot see audio from 1.5 s on
    assert torch.equal(a[:, :30], b[:, :30])
    assert not torch.allclose(a[:, 46:], b[:, 46:])


def test_the_speaker_enters_before_and_after_the_convolutions():
    audio, _ = clip(9)
    templ = torch.zeros(1, V, 3)
    D = tiny_config().speech.dim
    for path in ("convs", "fc"):
        model = tiny()
        with torch.no_grad():  # cut one of the two paths: the other still carries the speaker
            if path == "convs":
                model.encoder.convs[0].weight[:, D:] = 0
            else:
                model.encoder.fc.weight[:, -2:] = 0
        assert not torch.allclose(
            model.generate(audio, templ, styles=torch.tensor([0])),
            model.generate(audio, templ, styles=torch.tensor([1])),
        )


def test_save_load_gives_identical_output(tmp_path):
    model = tiny()
    model.set_feature_statistics(torch.randn(50, 16) * 2 + 1)
    path = save_model(model, tmp_path / "voca.safetensors")
    again = load_model(path)
    assert isinstance(again, VOCA) and again.cfg == model.cfg
    assert again.styles == ("a", "b") and again.num_vertices == V and again.motion_fps == FPS
    audio, _ = clip(8)
    templ = torch.randn(1, V, 3)
    torch.testing.assert_close(
        again.generate(audio, templ, styles=torch.tensor([1])),
        model.generate(audio, templ, styles=torch.tensor([1])),
        rtol=0,
        atol=0,
    )


def test_a_few_steps_lower_the_loss():
    model = tiny().train()
    audio, verts = clip(12, 3)
    templ = torch.zeros(1, V, 3)
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)
    first = model(audio, None, verts, templ, torch.tensor([0])).loss.item()
    for _ in range(25):
        opt.zero_grad()
        out = model(audio, None, verts, templ, torch.tensor([0]))
        out.loss.backward()
        opt.step()
    assert out.loss.item() < 0.7 * first
    assert out.vertices.shape == verts.shape


def test_wrong_vertex_count_is_a_clear_error():
    model = tiny()
    audio, verts = clip(5)
    with pytest.raises(TalkmeshError, match=f"meshes of {V} vertices"):
        model.generate(audio, torch.zeros(1, V + 1, 3), styles=torch.tensor([0]))
    with pytest.raises(TalkmeshError, match=f"meshes of {V} vertices"):
        model(audio, None, verts[:, :, :-1], torch.zeros(1, V - 1, 3), torch.tensor([0]))


@pytest.mark.parametrize("name", ["voca_synth", "voca_vocaset"])
def test_recipes(name):
    from talkmesh.training.trainer import DatasetInfo, load_recipe
    from talkmesh.training.voca import build_config

    recipe = load_recipe(CONFIGS / f"{name}.yaml", ["train.seed=3"])
    assert recipe.task == "voca" and recipe.train.seed == 3
    info = DatasetInfo(num_vertices=100, motion_fps=25.0, train_subjects=("x", "y", "z"))
    cfg = build_config(recipe.model, info)
    assert (cfg.num_vertices, cfg.motion_fps, cfg.styles) == (100, 25.0, ("x", "y", "z"))
    assert cfg.speech.frame_rate == 50.0  # 25 fps x 2 tokens per frame
    assert (cfg.window, cfg.conv_channels, cfg.hidden, cfg.latent) == (
        16,
        (32, 32, 64, 64),
        128,
        50,
    )
    assert cfg.speech.frozen and cfg.speech.kind in ("whisper", "wav2vec2")
    with pytest.raises(TalkmeshError, match="comes from the training data"):
        build_config({**recipe.model, "num_vertices": 3}, info)
    with pytest.raises(TalkmeshError, match="preset"):
        build_config({"preset": "biwi"}, info)


def test_train_one_epoch_end_to_end_and_load_the_release(tmp_path):
    from talkmesh.training.trainer import DataConfig, Recipe, TrainConfig, train

    root = tmp_path / "corpus"
    spec = DatasetSpec(
        kind="folder",
        motion_fps=FPS,
        stride=1,
        num_vertices=V,
        train_subjects=("p", "q"),
        faces_file="faces.ply",
    )
    templates = make_dataset(
        root, spec, ["p_s1", "p_s2", "q_s1", "q_s2", "r_s1"], frames=24, disk_fps=FPS, sr=SR
    )
    (root / "splits.json").write_text(
        json.dumps(
            {
                "train_subjects": ["p", "q"],
                "fps": FPS,
                "num_vertices": V,
                "faces_file": "faces.ply",
                "splits": {"train": {"p": ["s1", "s2"], "q": ["s1", "s2"]}, "val": {"r": ["s1"]}},
            }
        )
    )
    recipe = Recipe(
        task="voca",
        model={"speech": {"kind": "mel", "dim": 16}, "latent": 8, "hidden": 16},
        data=DataConfig(kind="folder", root=str(root), batch_size=2, max_seconds=0.5),
        train=TrainConfig(
            lr=1e-3, epochs=1, accelerator="cpu", log_every=1, out_dir=str(tmp_path / "run")
        ),
    )
    release = train(recipe, progress=False)
    model = load_model(release)
    assert isinstance(model, VOCA) and model.styles == ("p", "q") and model.num_vertices == V
    # prepare ran: a PCA decoder and feature statistics from the training data
    assert model.decoder.weight.abs().sum() > 0 and not torch.all(model.feature_std == 1)
    audio = torch.randn(1, SR)
    template = torch.from_numpy(templates["p"]).float()[None]
    out = model.generate(audio, template, styles=torch.tensor([1]))
    assert out.shape == (1, FPS, V, 3) and torch.isfinite(out).all()
    metrics = (tmp_path / "run" / "logs" / "metrics.csv").read_text()
    assert "train/velocity" in metrics and "val/loss" in metrics
