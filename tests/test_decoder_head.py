"""The head in CodeTalker's VQ decoder (``stage2.head_decoder``): the decoder hears how far the
head's lips stand apart at rest, zero at first (the same model), through every generation path
alike (naive, exact, fast, in chunks, streamed, batched with other heads, ONNX Runtime), saved
with the release and grown by the decoder refit (task codetalker-decoder)."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import STREAM_SPEECH, TINY_V, build_tiny_codetalker, decoder_recipe
from fixtures import TINY_WHISPER

from talkmesh.errors import TalkmeshError
from talkmesh.models.base import FrameRequest, next_frames
from talkmesh.models.codetalker.generate import PrefixFeedback
from talkmesh.models.codetalker.model import CodeTalker, Stage2Config
from talkmesh.models.codetalker.vq import DecoderStep
from talkmesh.models.release import load_model, save_model
from talkmesh.models.speech import SpeechEncoderConfig

PAIRS = (0, 1, 2, 3)  # two vertex pairs of the tiny mesh
WEIGHTS = torch.tensor([[0.6, 0.4]])
SR = 16_000
STYLE, DECODER = 0.01, 0.02  # the maps' noise: the heads differ and the frames still move


def with_face(model: CodeTalker, style: float, decoder: float) -> CodeTalker:
    """``model``'s weights with the head term in its style and its VQ decoder, the maps filled with
    noise scaled by ``style`` and ``decoder`` (0: as a refit begins)."""
    s2 = replace(
        model.cfg.stage2,
        head_pairs=PAIRS,
        head_mean=(0.1, 0.2),
        head_std=(0.05, 0.1),
        head_decoder=True,
    )
    grown = CodeTalker(replace(model.cfg, stage2=s2)).eval()
    missing = grown.load_state_dict(model.state_dict(), strict=False).missing_keys
    assert sorted(missing) == [
        "decoder_head.bias",
        "decoder_head.weight",
        "head_map.bias",
        "head_map.weight",
    ]
    torch.manual_seed(5)
    with torch.no_grad():
        for layer, scale in ((grown.head_map, style), (grown.decoder_head, decoder)):
            for p in layer.parameters():
                p.copy_(torch.randn_like(p) * scale)
    return grown


def heads(seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """Two (1, V, 3) templates alike but for their first lip pair: 0.05 and 0.3 apart."""
    base = torch.randn(1, TINY_V, 3, generator=torch.Generator().manual_seed(seed)) * 0.1
    near, far = base.clone(), base.clone()
    near[0, 1] = base[0, 0] - torch.tensor([0.0, 0.05, 0.0])
    far[0, 1] = base[0, 0] - torch.tensor([0.0, 0.3, 0.0])
    return near, far


def audio(seconds: float = 0.6, seed: int = 1) -> torch.Tensor:
    return torch.randn(1, int(seconds * SR), generator=torch.Generator().manual_seed(seed)) * 0.1


def offsets(model: CodeTalker, sound: torch.Tensor, template: torch.Tensor, **kw) -> torch.Tensor:
    return model.generate(sound, template, style_weights=WEIGHTS, **kw) - template[:, None]


@pytest.mark.parametrize("causal", [False, True])
def test_a_model_given_the_decoder_term_is_the_same_model_at_first(causal):
    base = build_tiny_codetalker(vq_layers=2, causal=causal)
    styled = with_face(base, STYLE, 0.0)  # the style's term as learned, the decoder's zero
    fresh = with_face(base, 0.0, 0.0)
    near, _ = heads()
    sound = audio()
    assert torch.equal(offsets(fresh, sound, near), offsets(base, sound, near))
    assert fresh.decoder_face(near).shape == (1, base.cfg.vq.hidden)
    assert not fresh.decoder_face(near).any()
    # the style's term alone: the VQ decoder draws what it drew without the decoder's term
    plain = CodeTalker(replace(styled.cfg, stage2=replace(styled.cfg.stage2, head_decoder=False)))
    state = {k: v for k, v in styled.state_dict().items() if not k.startswith("decoder_head.")}
    plain.load_state_dict(state, strict=True)
    assert plain.decoder_head is None and plain.decoder_face(near) is None
    assert torch.equal(offsets(styled, sound, near), offsets(plain.eval(), sound, near))


def test_head_decoder_needs_the_head_pairs():
    with pytest.raises(ValueError, match="head_decoder"):
        Stage2Config(styles=("a",), head_decoder=True)
    cfg = Stage2Config(
        styles=("a",), head_pairs=(0, 1), head_mean=(0.1,), head_std=(0.1,), head_decoder=True
    )
    assert cfg.head_decoder


def test_the_decoder_draws_each_heads_lips_and_reads_the_head_term_of_the_style():
    model = with_face(build_tiny_codetalker(vq_layers=2, causal=True), 0.0, DECODER)
    near, far = heads()
    face_near, face_far = model.decoder_face(near), model.decoder_face(far)
    # linear in the standardised distances: (0.3 - 0.05) / 0.05 along pair 0's column
    want = model.decoder_head.weight[:, 0] * (0.25 / 0.05) * model.head_scale
    torch.testing.assert_close((face_far - face_near)[0], want, atol=1e-4, rtol=1e-4)
    # no template: the training templates' average head (standardised distances 0)
    assert torch.equal(model.decoder_face(None), model.decoder_head.bias[None])
    codes = torch.randint(0, model.codebook_size, (1, 12, model.cfg.vq.components))
    with torch.no_grad():
        drawn_near = model.vqvae.decode(codes, face=face_near)
        drawn_far = model.vqvae.decode(codes, face=face_far)
    assert (drawn_near - drawn_far).abs().max() > 1e-2  # the same codes, other lips
    # the style's term is zero here: the motion differs through the VQ decoder alone
    sound = audio()
    assert torch.equal(model.style_vector(None, WEIGHTS, near), model.style_vector(None, WEIGHTS))
    assert (offsets(model, sound, near) - offsets(model, sound, far)).abs().max() > 1e-2


@pytest.mark.parametrize("causal", [False, True])
def test_every_generation_path_hears_the_head_alike(causal):
    model = with_face(build_tiny_codetalker(vq_layers=2, causal=causal), STYLE, DECODER)
    near, far = heads()
    sound = audio()
    want = {}
    for name, head in (("near", near), ("far", far)):
        naive = offsets(model, sound, head, mode="naive")
        exact = offsets(model, sound, head, mode="exact")
        torch.testing.assert_close(exact, naive, atol=1e-5, rtol=1e-4)
        if causal:  # a bidirectional decoder's fast mode approximates the loop
            torch.testing.assert_close(offsets(model, sound, head), naive, atol=1e-5, rtol=1e-4)
            one = offsets(model, sound, head, block=1)
            torch.testing.assert_close(one, naive, atol=1e-5, rtol=1e-4)
            chunks = model.generate_chunks(sound, head, style_weights=WEIGHTS, chunk=4)
            chunked = torch.cat(list(chunks), 1) - head[:, None]
            torch.testing.assert_close(chunked, naive, atol=1e-5, rtol=1e-4)
        want[name] = naive
    assert naive.std(1).max() > 1e-3  # the frames move
    assert (want["near"] - want["far"]).abs().max() > 1e-2
    # a batch of both heads: each row as alone
    mode = "fast" if causal else "exact"
    both = model.generate(
        sound.repeat(2, 1), torch.cat([near, far]), style_weights=WEIGHTS.repeat(2, 1), mode=mode
    )
    both = both - torch.cat([near, far])[:, None]
    for row, head in enumerate((near, far)):
        alone = offsets(model, sound, head, mode=mode)
        torch.testing.assert_close(both[row : row + 1], alone, atol=1e-5, rtol=1e-4)


def test_without_attention_in_the_vq_decoder_fast_and_windowed_decoding_equal_the_loop():
    # then the bidirectional decoder's cached feedback and its windows are exact
    model = with_face(build_tiny_codetalker(vq_layers=0), STYLE, DECODER)
    near, far = heads()
    sound = audio()
    for head in (near, far):
        naive = offsets(model, sound, head, mode="naive")
        torch.testing.assert_close(offsets(model, sound, head), naive, atol=1e-5, rtol=1e-4)
    assert (naive - offsets(model, sound, near)).abs().max() > 1e-2
    codes = torch.randint(0, model.codebook_size, (1, 20, model.cfg.vq.components))
    face = model.decoder_face(far)
    with torch.no_grad():
        whole = model.vqvae.decode(codes, face=face)
        torch.testing.assert_close(model.vqvae.decode(codes, 4, 2, face=face), whole)
        assert (whole - model.vqvae.decode(codes, 4, 2)).abs().max() > 1e-3


def test_teacher_forcing_and_reconstruction_decode_with_the_head():
    model = with_face(build_tiny_codetalker(vq_layers=2, causal=True), STYLE, DECODER)
    near, far = heads()
    sound = audio()
    style = torch.tensor([1])
    for head in (near, far):
        generated = model.generate(sound, head, styles=style, mode="naive")
        # fed back the generated motion, the causal teacher-forced pass computes that motion
        with torch.no_grad():
            out = model(sound, None, generated, head, style)
        torch.testing.assert_close(
            out.motion, (generated - head[:, None]).flatten(2), atol=1e-4, rtol=1e-3
        )
    vertices = near[:, None] + torch.randn(1, 8, TINY_V, 3) * 0.01
    with torch.no_grad():
        codes = model.motion_codes(vertices, near)
        want = model.vqvae.decode(codes, face=model.decoder_face(near)) + near.flatten(1)[:, None]
        got = model.reconstruct(vertices, near)
        other = model.reconstruct(vertices - near[:, None] + far[:, None], far) - far[:, None]
    torch.testing.assert_close(got.flatten(2), want, atol=1e-5, rtol=1e-4)
    assert (other - (got - near[:, None])).abs().max() > 1e-3


def test_the_decoder_steps_and_the_prefix_feedback_add_the_face():
    causal = with_face(build_tiny_codetalker(vq_layers=2, causal=True), 0.0, DECODER)
    bidirectional = with_face(build_tiny_codetalker(vq_layers=2), 0.0, DECODER)
    near, far = heads()
    face = torch.cat([causal.decoder_face(near), causal.decoder_face(far)])
    z = torch.randn(2, 14, 4, 8, generator=torch.Generator().manual_seed(3))
    with torch.inference_mode():
        dec = causal.vqvae.decoder
        step = DecoderStep(dec, face)
        steps = torch.cat([step.hidden(z[:, t : t + 1]) for t in range(14)], 1)
        torch.testing.assert_close(steps, dec.hidden(z, face=face), atol=1e-5, rtol=1e-4)
        dec = bidirectional.vqvae.decoder
        face = torch.cat([bidirectional.decoder_face(near), bidirectional.decoder_face(far)])
        feedback = PrefixFeedback(dec, face)
        for t in range(1, 15):
            want = dec.hidden(z[:, :t], face=face)[:, -1:]
            torch.testing.assert_close(feedback(z[:, :t], 0), want, atol=1e-5, rtol=1e-5)
        assert feedback.fixed is not None  # the incremental path ran
        assert (dec.hidden(z, face=face) - dec.hidden(z)).abs().max() > 1e-3


def test_streams_of_other_heads_stepped_together_equal_offline_generation(tmp_path):
    base = build_tiny_codetalker(causal=True, attention_window=7, speech=STREAM_SPEECH)
    path = save_model(with_face(base, STYLE, DECODER), tmp_path / "face.safetensors")
    net = load_model(path)
    near, far = heads()
    sound = np.random.default_rng(2).normal(0, 0.1, int(1.2 * SR)).astype(np.float32)
    frames = 30
    streams = [
        net.open_frame_stream(WEIGHTS[0].numpy(), 0.0, head[0].numpy()) for head in (near, far)
    ]
    got: list[list[np.ndarray]] = [[], []]
    for t in range(frames):
        live = [k for k in range(2) if t >= 3 * k]  # the second joins at frame 3
        requests = [FrameRequest(streams[k], sound, 0, len(got[k])) for k in live]
        for k, motion in zip(live, next_frames(requests)):
            got[k].append(motion)
    offline = []
    net.speech.set_lookahead(0.0)  # the streams' (generate's default is the largest trained)
    for k, head in enumerate((near, far)):
        want = offsets(net, torch.from_numpy(sound)[None], head)[0, : len(got[k])]
        np.testing.assert_allclose(np.stack(got[k]), want.flatten(1).numpy(), atol=2e-5)
        offline.append(want)
    assert (offline[0][:20] - offline[1][:20]).abs().max() > 1e-2  # the heads are told apart


def test_the_release_keeps_the_decoder_term_and_old_releases_load_without_it(tmp_path):
    model = with_face(build_tiny_codetalker(causal=True), STYLE, DECODER)
    loaded = load_model(save_model(model, tmp_path / "m.safetensors"))
    assert loaded.cfg == model.cfg and loaded.cfg.stage2.head_decoder
    near, _ = heads()
    sound = audio()
    assert torch.equal(offsets(loaded, sound, near), offsets(model, sound, near))
    old = Path(__file__).parent / "fixtures" / "old_releases" / "codetalker.safetensors"
    before = load_model(old)  # written before the option
    assert not before.cfg.stage2.head_decoder and before.decoder_head is None
    bundled = load_model("codetalker-synth")  # the bundled model hears the face
    assert bundled.cfg.stage2.head_decoder and bundled.decoder_head is not None


def test_onnx_runtime_feeds_the_face_as_pytorch_does(tmp_path):
    pytest.importorskip("onnxruntime")
    from talkmesh.models.onnx import OnnxModel, export_onnx

    speech = SpeechEncoderConfig(kind="whisper", dim=16, hf_config=TINY_WHISPER)
    base = build_tiny_codetalker(speech=speech, causal=True, attention_window=7)
    model = with_face(base, STYLE, DECODER)
    export_onnx(model, tmp_path / "face.onnx")
    export_onnx(base, tmp_path / "plain.onnx")
    runtime, plain = OnnxModel(tmp_path / "face.onnx"), OnnxModel(tmp_path / "plain.onnx")
    names = [i.name for i in runtime.step.get_inputs()]
    assert names[:5] == ["feature", "t", "style", "face", "x_in"]
    assert "face" not in [i.name for i in plain.step.get_inputs()] and plain.face() is None
    near, far = heads()
    with torch.no_grad():
        want_face = model.decoder_face(far).numpy()
    assert np.abs(runtime.face(far[0].numpy()) - want_face).max() <= 1e-5
    sound = audio(1.0)
    results = []
    for head in (near, far):
        want = offsets(model, sound, head)
        got = runtime.generate(sound, head, style_weights=WEIGHTS) - head[:, None]
        assert (got - want).abs().max() <= 1e-4 * want.abs().max()
        results.append(got)
    assert (results[0] - results[1]).abs().max() > 1e-2
    # two streams of other heads in one step, each as alone
    feats = np.random.default_rng(0).normal(size=(2, 6, 16)).astype(np.float32)
    style = runtime.style(None).repeat(2, 0)
    faces = np.concatenate([runtime.face(h[0].numpy()) for h in (near, far)])
    state, together = runtime.start(style), []
    for t in range(6):
        motion, state = runtime.step_frames(feats[:, t], np.array([t, t]), style, state, faces)
        together.append(motion)
    for b in range(2):
        state = runtime.start(style[b : b + 1])
        for t in range(6):
            motion, state = runtime.step_frames(
                feats[b, t][None], np.array([t]), style[:1], state, faces[b : b + 1]
            )
            np.testing.assert_allclose(motion[0], together[t][b], atol=1e-6)
    assert np.abs(together[-1][0] - together[-1][1]).max() > 1e-3


def test_the_decoder_refit_grows_and_trains_the_decoder_term_alone(tiny_corpus, tmp_path):
    pytest.importorskip("lightning")
    from talkmesh.datasets.reader import open_dataset
    from talkmesh.training.codetalker import FINETUNE, _build_finetune
    from talkmesh.training.trainer import dataset_info, load_recipe, train

    data = open_dataset("synth", tiny_corpus, "train")
    subjects = tuple(data.spec.train_subjects)
    torch.manual_seed(0)
    plain = CodeTalker(CodeTalker.tiny_config(data.spec.num_vertices, subjects))
    s2 = replace(plain.cfg.stage2, head_pairs=PAIRS, head_mean=(0.1, 0.2), head_std=(0.05, 0.1))
    base = CodeTalker(replace(plain.cfg, stage2=s2))
    base.load_state_dict(plain.state_dict(), strict=False)
    save_model(base, tmp_path / "base.safetensors")
    save_model(plain, tmp_path / "plain.safetensors")
    recipe = tmp_path / "r.yaml"
    decoder_recipe(
        recipe,
        tmp_path / "base.safetensors",
        tiny_corpus,
        tmp_path / "run",
        "model: {head_decoder: true}\n",
    )
    release = train(load_recipe(recipe), progress=False)
    refit = load_model(release)
    assert refit.cfg == replace(base.cfg, stage2=replace(s2, head_decoder=True))
    before, after = base.state_dict(), refit.state_dict()
    assert set(after) - set(before) == {"decoder_head.weight", "decoder_head.bias"}
    changed = {k for k in before if not torch.equal(before[k], after[k])}
    assert changed and all(k.startswith("vqvae.decoder.") for k in changed), changed
    assert refit.decoder_head.weight.abs().max() > 0  # it learned, from zero
    # a release without the style's head term has no lip pairs to read: refused in one line
    decoder_recipe(
        recipe,
        tmp_path / "plain.safetensors",
        tiny_corpus,
        tmp_path / "bad",
        "model: {head_decoder: true}\n",
    )
    with pytest.raises(TalkmeshError, match="head_pairs") as refused:
        train(load_recipe(recipe), progress=False)
    assert "\n" not in str(refused.value)
    decoder_recipe(
        recipe,
        tmp_path / "base.safetensors",
        tiny_corpus,
        tmp_path / "odd",
        "model: {head_decoder: 1}\n",
    )
    with pytest.raises(TalkmeshError, match="may only say head_decoder: true"):
        train(load_recipe(recipe), progress=False)
    assert not (tmp_path / "bad").exists() and not (tmp_path / "odd").exists()
    # the speech stage's fine-tune keeps the decoder's term with the frozen motion stage
    net = _build_finetune({}, dataset_info(data), release)
    assert not net.decoder_head.weight.requires_grad
    trained = {id(p) for p in FINETUNE.parameters(net)}
    assert not trained & {id(p) for p in net.decoder_head.parameters()}


def test_stage1_and_the_decoder_step_decode_each_batch_row_with_its_head():
    from talkmesh.training import codetalker as tasks
    from talkmesh.training.trainer import TorchBatch

    model = with_face(build_tiny_codetalker(causal=True), STYLE, DECODER)
    near, far = heads()
    templates = torch.cat([near, far])
    vertices = templates[:, None] + torch.randn(2, 6, TINY_V, 3) * 0.01
    mask = torch.ones(2, 6, dtype=torch.bool)
    batch = TorchBatch(["a", "b"], None, None, vertices, templates, mask, torch.tensor([0, 1]))
    with torch.no_grad():
        want = model.vqvae.decode(
            model.motion_codes(vertices, templates), face=model.decoder_face(templates)
        )
        for step in (tasks._step_stage1, tasks._step_decoder):
            torch.testing.assert_close(step(model.eval(), batch).motion, want)
    head = {id(p) for p in model.decoder_head.parameters()}
    for task in (tasks.STAGE1, tasks.DECODER):
        assert head <= {id(p) for p in task.parameters(model)}


def test_the_decoder_head_recipe_grows_the_bundled_models_decoder():
    pytest.importorskip("yaml")
    from talkmesh.training.trainer import _init_path, load_recipe, task_spec

    root = Path(__file__).parents[1] / "configs"
    recipe = load_recipe(root / "codetalker_decoder_head.yaml")
    refit = load_recipe(root / "codetalker_decoder_refit.yaml")
    close = load_recipe(root / "codetalker_multilingual_close.yaml")
    assert recipe.task == "codetalker-decoder" and recipe.model == {"head_decoder": True}
    assert recipe.data == refit.data and recipe.train.lip_close_weight > 0
    # it refits the decoder of the speech stage trained with the closures counted more
    assert recipe.init == f"{close.train.out_dir}/model.safetensors"
    assert close.task == "codetalker-finetune" and close.train.lip_close_weight > 0
    assert _init_path(close.init).name == "codetalker-synth.safetensors"
    assert task_spec(recipe.task).name == "codetalker-decoder"
    assert load_model("codetalker-synth").cfg.stage2.head_pairs  # what head_decoder reads


def test_a_speech_stage_on_a_motion_stage_refitted_with_the_face_keeps_its_face_term(
    tiny_corpus, tmp_path
):
    """task codetalker-stage2 on such a release (the streaming model on the bundled one): the
    VQ decoder's face term and its lip pairs come with the VQ-VAE, frozen with it."""
    from talkmesh.config import to_dict
    from talkmesh.datasets.reader import open_dataset
    from talkmesh.training.codetalker import STAGE2, _build_stage2
    from talkmesh.training.trainer import dataset_info

    data = open_dataset("synth", tiny_corpus, "train")
    subjects = tuple(data.spec.train_subjects)
    torch.manual_seed(0)
    plain = CodeTalker(CodeTalker.tiny_config(data.spec.num_vertices, subjects))
    save_model(plain, tmp_path / "plain.safetensors")
    source = with_face(plain, STYLE, DECODER)
    save_model(source, tmp_path / "face.safetensors")
    source = load_model(tmp_path / "face.safetensors")
    recipe = to_dict(plain.cfg)  # the release's network, as a recipe's model section says it
    net = _build_stage2(recipe, dataset_info(data), tmp_path / "face.safetensors")
    s2 = net.cfg.stage2
    assert s2.head_decoder and s2.head_pairs == source.cfg.stage2.head_pairs
    assert (s2.head_mean, s2.head_std) == (source.cfg.stage2.head_mean, source.cfg.stage2.head_std)
    assert torch.equal(net.decoder_head.weight, source.decoder_head.weight)
    assert not net.head_map.weight.any()  # the style's term starts at zero: learned in stage 2
    trained = {id(p) for p in STAGE2.parameters(net)}
    assert not trained & {id(p) for p in net.decoder_head.parameters()}
    assert {id(p) for p in net.head_map.parameters()} <= trained
    template = torch.from_numpy(data[0].template)[None]
    assert torch.equal(net.decoder_face(template), source.decoder_face(template))
    # a release without the face term gives none
    bare = _build_stage2(recipe, dataset_info(data), tmp_path / "plain.safetensors")
    assert bare.decoder_head is None and not bare.cfg.stage2.head_pairs
