"""CodeTalker invariants on tiny configurations."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from talkmesh.errors import TalkmeshError
from talkmesh.models.codetalker.generate import FrameGenerator, generate_fast
from talkmesh.models.codetalker.model import CodeTalker, Stage2Config
from talkmesh.models.codetalker.vq import DecoderStep, Quantizer, VQConfig
from talkmesh.models.int8 import Int8Conv1d, Int8Linear, int8_layers, quantize_int8
from talkmesh.models.layers import KVCache, temporal_bias
from talkmesh.models.release import load_model, save_model
from talkmesh.models.speech import SpeechEncoderConfig

SR = 16_000
CONFIGS = Path(__file__).resolve().parents[1] / "configs"
FPS = 30


def clip(frames: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return torch.randn(1, frames * SR // FPS, generator=g), torch.randn(
        1, frames, 20, 3, generator=g
    ) * 0.01


def test_quantize_lookup_round_trip():
    vq = Quantizer(16, 8, 0.25).eval()
    codes = torch.randint(0, 16, (2, 5, 4))
    z = vq.lookup(codes) + 1e-4 * torch.randn(2, 5, 4, 8)  # near the codebook entries
    z_q, found, loss = vq(z)
    assert torch.equal(found, codes)
    torch.testing.assert_close(z_q, vq.lookup(found))
    assert loss.item() < 1e-6


def test_quantizer_straight_through_and_ema():
    vq = Quantizer(16, 8, 0.25, ema=True, restart=True).train()
    z = torch.randn(2, 5, 4, 8, requires_grad=True)
    z_q, _, loss = vq(z)
    (z_q.sum() + loss).backward()
    assert z.grad is not None and torch.isfinite(z.grad).all()
    assert vq.usage.sum() > 0 and 1 <= vq.perplexity() <= 16


def test_vqvae_reconstructs_after_a_few_steps(tiny_codetalker):
    model = tiny_codetalker()
    motion = clip(10)[1].flatten(2)
    opt = torch.optim.Adam(model.vqvae.parameters(), lr=3e-3)
    model.train()
    first = model.vqvae(motion).loss.item()
    for _ in range(30):
        opt.zero_grad()
        out = model.vqvae(motion)
        out.loss.backward()
        opt.step()
    assert out.loss.item() < first
    assert out.motion.shape == motion.shape


@pytest.mark.parametrize("speech", ["mel", "wav2vec2"])
def test_padded_batch_equals_single_samples(speech, tiny_codetalker):
    model = tiny_codetalker(speech=speech)
    (a_audio, a_v), (b_audio, b_v) = clip(7, 1), clip(11, 2)
    audio = torch.zeros(2, b_audio.shape[1])
    audio[0, : a_audio.shape[1]], audio[1] = a_audio[0], b_audio[0]
    verts = torch.zeros(2, 11, 20, 3)
    verts[0, :7], verts[1] = a_v[0], b_v[0]
    mask = torch.zeros(2, 11, dtype=torch.bool)
    mask[0, :7], mask[1] = True, True
    lengths = torch.tensor([a_audio.shape[1], b_audio.shape[1]])
    templ = torch.zeros(2, 20, 3)
    styles = torch.tensor([0, 1])
    with torch.no_grad():
        batch = model(audio, lengths, verts, templ, styles, mask)
        alone_a = model(a_audio, None, a_v, templ[:1], styles[:1])
        alone_b = model(b_audio, None, b_v, templ[:1], styles[1:])
    torch.testing.assert_close(batch.motion[0, :7], alone_a.motion[0], atol=1e-5, rtol=1e-4)
    torch.testing.assert_close(batch.motion[1], alone_b.motion[0], atol=1e-5, rtol=1e-4)


def test_fast_generation_equals_naive_when_the_vq_decoder_has_no_attention(tiny_codetalker):
    model = tiny_codetalker(
        vq_layers=0
    )  # then the only difference (bidirectional attention) is gone
    audio, _ = clip(15)
    templ = torch.zeros(1, 20, 3)
    naive = model.generate(audio, templ, styles=torch.tensor([1]), mode="naive")
    fast = model.generate(audio, templ, styles=torch.tensor([1]), mode="fast")
    torch.testing.assert_close(fast, naive)
    assert naive.shape == (1, 15, 20, 3) and naive.std(dim=1).max() > 0


def test_fast_generation_is_causal_in_its_codes(tiny_codetalker):
    model = tiny_codetalker()
    audio, _ = clip(20)
    t, lookahead = 9, 4  # the mel encoder sees 100 ms (3 frames) ahead
    changed = audio.clone()
    start = (t + lookahead) * SR // FPS
    changed[:, start:] = torch.randn_like(changed[:, start:])
    style = torch.tensor([0])
    tok_a, tok_b = model.audio_tokens(audio, None, 20), model.audio_tokens(changed, None, 20)
    assert torch.equal(tok_a[:, : t + 1], tok_b[:, : t + 1])  # the speech features are causal
    assert not torch.allclose(tok_a[:, t + 1 + lookahead :], tok_b[:, t + 1 + lookahead :])
    # ... and the decoder sees nothing later: change every later token and the codes up to t stay
    tok_c = tok_a.clone()
    tok_c[:, t + 1 :] = torch.randn_like(tok_c[:, t + 1 :]) * 10
    a, _ = generate_fast(model, model.style_vector(style), model.cross_terms(tok_a), 20)
    c, _ = generate_fast(model, model.style_vector(style), model.cross_terms(tok_c), 20)
    assert torch.equal(a[:, : t + 1], c[:, : t + 1])
    assert not torch.equal(a, c)


def test_style_interpolation_and_unseen_speakers(tiny_codetalker):
    model = tiny_codetalker()
    audio, _ = clip(6)
    templ = torch.zeros(1, 20, 3)
    pure = model.generate(audio, templ, styles=torch.tensor([0]))
    mixed = model.generate(audio, templ, style_weights=torch.tensor([[1.0, 0.0]]))
    torch.testing.assert_close(pure, mixed)
    with pytest.raises(TalkmeshError, match="unseen speaker"):
        model.generate(audio, templ, styles=torch.tensor([-1]))


def test_temporal_bias_is_periodic_and_causal():
    b = temporal_bias(2, 4, 4, period=2)
    assert (
        torch.isinf(b[0, 0, 1])
        and b[0, 3, 0] == -0.25
        and b[1, 3, 0] == -1 / 16
        and b[0, 1, 0] == 0
    )


def test_save_load_gives_identical_output(tmp_path, tiny_codetalker):
    model = tiny_codetalker()
    path = save_model(model, tmp_path / "m.safetensors")
    again = load_model(path)
    import talkmesh

    assert talkmesh.load_model is load_model  # the package's own entry point
    audio, _ = clip(8)
    templ = torch.zeros(1, 20, 3)
    torch.testing.assert_close(
        again.generate(audio, templ, styles=torch.tensor([0])),
        model.generate(audio, templ, styles=torch.tensor([0])),
    )
    (tmp_path / "bad.safetensors").write_bytes(b"not a model")
    with pytest.raises(TalkmeshError, match="bad.safetensors"):
        load_model(tmp_path / "bad.safetensors")


def test_wav2vec2_encoder_behind_the_same_interface(tiny_codetalker):
    model = tiny_codetalker(speech="wav2vec2")
    audio, verts = clip(9)
    out = model(audio, None, verts, torch.zeros(1, 20, 3), torch.tensor([0]))
    assert out.motion.shape == (1, 9, 60) and torch.isfinite(out.loss)
    cnn = model.speech.model.feature_extractor
    assert not any(p.requires_grad for p in cnn.parameters())  # the CNN stays frozen


def test_codebook_starts_at_encoder_outputs_and_motion_scale_is_per_coordinate(tiny_codetalker):
    assert bool(Quantizer(16, 8, 0.25).initialised)  # default: the paper's random codebook
    vq = Quantizer(16, 8, 0.25, init_from_data=True).train()
    z = torch.randn(2, 5, 4, 8) * 3
    vq(z)
    assert bool(vq.initialised)
    dist = torch.cdist(vq.codebook.detach(), z.reshape(-1, 8)).min(1).values
    assert dist.max() < 0.1  # every code sits on an encoder output
    model = tiny_codetalker()
    motion = torch.zeros(50, 60)
    motion[:, 0] = torch.randn(50) * 2.0  # one moving coordinate, the rest still
    model.vqvae.set_scale(motion)
    scale = model.vqvae.encoder.scale
    assert scale[0] == pytest.approx(float(motion[:, 0].std()), rel=1e-5)
    assert torch.allclose(scale[1:], scale[0] * 0.05)  # still coordinates get the floor


@pytest.mark.parametrize("name", ["codetalker_synth", "codetalker_vocaset", "codetalker_biwi"])
def test_recipes_have_two_stages_and_the_paper_sizes(name):
    pytest.importorskip("yaml")
    from talkmesh.training.codetalker import build_config
    from talkmesh.training.trainer import DatasetInfo, load_recipes

    stages = load_recipes(CONFIGS / f"{name}.yaml", ["train.seed=3", "stages.speech.train.lr=2e-4"])
    assert [r.task for _, r in stages] == ["codetalker-stage1", "codetalker-stage2"]
    assert all(r.train.seed == 3 for _, r in stages) and stages[1][1].train.lr == 2e-4
    assert stages[1][1].init == f"{stages[0][1].train.out_dir}/model.safetensors"
    info = DatasetInfo(num_vertices=100, motion_fps=25.0, train_subjects=("a", "b"))
    cfg = build_config(stages[1][1].model, info)
    assert cfg.vq.num_vertices == 100 and cfg.stage2.styles == ("a", "b")
    if name == "codetalker_vocaset":
        assert (cfg.vq.components, cfg.vq.code_dim, cfg.stage2.layers) == (16, 64, 6)
    if name == "codetalker_biwi":
        assert (cfg.vq.components, cfg.vq.code_dim, cfg.stage2.layers) == (8, 128, 12)
        assert cfg.stage2.period == 25 and cfg.stage2.audio_tokens_per_frame == 2
        assert cfg.stage2.speech.frame_rate == 50.0  # 25 fps x 2 tokens
    if name != "codetalker_synth":
        assert stages[0][1].train.epochs == 200 and stages[1][1].train.epochs == 100
        assert cfg.stage2.speech.kind == "wav2vec2" and cfg.vq.loss == "l1"


def test_recipe_stage_errors(tmp_path):
    pytest.importorskip("yaml")
    from talkmesh.training.trainer import load_recipes

    bad = tmp_path / "r.yaml"
    bad.write_text("stages:\n  a: {task: nothing}\n")
    with pytest.raises(TalkmeshError, match="unknown task"):
        load_recipes(bad)
    bad.write_text("stages: [1, 2]\n")
    with pytest.raises(TalkmeshError, match="must map stage names"):
        load_recipes(bad)


def test_windowed_vq_decode_equals_whole_decode_without_attention(tiny_codetalker):
    model = tiny_codetalker(
        vq_layers=0
    )  # the conv sees 2 frames each side: 3 frames of context suffice
    codes = torch.randint(0, 16, (2, 40, 4))
    whole = model.vqvae.decode(codes)
    torch.testing.assert_close(model.vqvae.decode(codes, window=7, context=3), whole)
    attn = tiny_codetalker(
        vq_layers=1
    )  # with attention the windows differ a little, but shapes agree
    assert attn.vqvae.decode(codes, window=7, context=3).shape == whole.shape


def test_long_audio_goes_through_wav2vec2_in_windows(monkeypatch, tiny_codetalker):
    from dataclasses import replace

    model = tiny_codetalker(speech="wav2vec2")
    enc = model.speech
    enc.cfg = replace(enc.cfg, window_seconds=0.5, context_seconds=0.25)
    seen = []
    inner = enc.model.forward
    monkeypatch.setattr(
        enc.model, "forward", lambda a, **k: seen.append(a.shape[1]) or inner(a, **k)
    )
    audio = torch.randn(1, 3 * SR)
    with torch.no_grad():
        feats = enc(audio, None, 90)
        full = inner(audio).last_hidden_state
    assert feats.shape == (1, 90, enc.dim) and len(seen) == 6 and max(seen) <= 1.0 * SR
    windowed = enc.features(audio)
    assert abs(windowed.shape[1] - full.shape[1]) <= 1  # the same feature rate as one pass
    lengths = torch.tensor([3 * SR, 2 * SR])  # a padded batch: each sample on its own windows
    batch = torch.cat([audio, torch.cat([audio[:, : 2 * SR], torch.zeros(1, SR)], 1)])
    with torch.no_grad():
        out = enc(batch, lengths, 90)
        alone = enc(audio[:, : 2 * SR], None, 60)
    torch.testing.assert_close(out[1:, :60], alone)  # its 2 s are the batch's first 60 frames


def test_kv_cache_keeps_the_last_window_in_place():

    cache, ks = KVCache(window=5), []
    for step in range(23):
        k = torch.full((1, 2, 1, 3), float(step))
        ks.append(k)
        got_k, got_v = cache.append(k, -k)
        want = torch.cat(ks, dim=2)[:, :, -5:]
        torch.testing.assert_close(got_k, want)
        torch.testing.assert_close(got_v, -want)
    assert cache.k.shape[2] == 10  # twice the window, never more


def test_kv_cache_takes_several_rows_and_gives_the_last_ones_back():

    cache, kept = KVCache(window=5), []  # ``kept``: the rows the cache should hold, in order
    g = torch.Generator().manual_seed(0)
    for _ in range(30):
        t = int(torch.randint(1, 8, (1,), generator=g))
        k = torch.randn(1, 2, t, 3, generator=g)
        got_k, got_v = cache.append(k, 2 * k)
        kept.append(k)
        want = torch.cat(kept, dim=2)[:, :, -(5 + t - 1) :]  # each new row's own window
        torch.testing.assert_close(got_k, want)
        torch.testing.assert_close(got_v, 2 * want)
        back = int(torch.randint(0, t + 1, (1,), generator=g))
        cache.drop(back)
        kept[-1] = k[:, :, : t - back]


def _count_passes(monkeypatch) -> list[tuple[int, int, int]]:
    """Record (frames, guesses, frames kept) of every FrameGenerator.block pass."""

    passes, block = [], FrameGenerator.block

    def counted(self, cross, drafts):
        out = block(self, cross, drafts)
        passes.append((cross[0].shape[1], drafts.shape[1], out[0].shape[1]))
        return out

    monkeypatch.setattr(FrameGenerator, "block", counted)
    return passes


@pytest.mark.parametrize("causal", [False, True])
def test_fast_generation_in_passes_equals_frame_by_frame(causal, monkeypatch, tiny_codetalker):
    from dataclasses import replace

    model = tiny_codetalker(vq_layers=2, causal=causal)
    model.cfg = replace(model.cfg, stage2=replace(model.cfg.stage2, attention_window=7))
    with torch.no_grad():  # feedback strong enough that many guesses fail and are taken back
        model.motion_map.weight.mul_(100.0)
    audio = torch.cat([clip(40, seed=1)[0], clip(40, seed=2)[0]])  # a batch of two
    style = model.style_vector(torch.tensor([0, 1]))
    cross = model.cross_terms(model.audio_tokens(audio, None, 40))
    passes = _count_passes(monkeypatch)
    one, one_motion = generate_fast(model, style, cross, 40, block=1)
    assert all(p == (1, 0, 1) for p in passes) and len(passes) == 40
    passes.clear()
    many, motion = generate_fast(model, style, cross, 40, block=16)
    assert torch.equal(many, one)  # the same codes, past both attention windows
    if causal:
        torch.testing.assert_close(motion, one_motion, atol=1e-5, rtol=1e-4)
    assert len(passes) < 40  # passes kept several frames ...
    assert any(kept <= guesses for _, guesses, kept in passes)  # ... and took some back
    assert max(frames for frames, _, _ in passes) == 16
    templ = torch.randn(2, 20, 3)
    torch.testing.assert_close(
        model.generate(audio, templ, styles=torch.tensor([0, 1])),
        model.generate(audio, templ, styles=torch.tensor([0, 1]), block=1),
    )


def test_a_pass_without_guesses_guesses_that_the_codes_hold_still(monkeypatch, tiny_codetalker):
    model = tiny_codetalker(vq_layers=2)
    torch.nn.init.zeros_(model.feat_map.weight)  # every frame gets the same codes
    style = model.style_vector(torch.tensor([0]))
    cross = model.cross_terms(model.audio_tokens(clip(12)[0], None, 12))
    steps, _ = generate_fast(model, style, cross, 12, block=1)
    assert (steps == steps[:, :1]).all()
    passes = _count_passes(monkeypatch)
    codes, _ = generate_fast(model, style, cross, 12, block=16)
    assert torch.equal(codes, steps)
    assert passes == [(1, 0, 1), (11, 0, 11)]  # frame 0 alone, then the guesses all held


def test_when_guesses_keep_failing_fast_mode_runs_frames_one_at_a_time(
    monkeypatch, tiny_codetalker
):

    model = tiny_codetalker(vq_layers=2)
    style = model.style_vector(torch.tensor([0]))
    cross = model.cross_terms(model.audio_tokens(clip(80)[0], None, 80))
    steps, _ = generate_fast(model, style, cross, 80, block=1)
    block, passes = FrameGenerator.block, []

    def wrong_guesses(self, cross, drafts):  # every guess fails: each pass keeps one frame
        out = block(self, cross, (drafts + 1) % 16)
        passes.append((cross[0].shape[1], out[0].shape[1]))
        return out

    monkeypatch.setattr(FrameGenerator, "block", wrong_guesses)
    codes, _ = generate_fast(model, style, cross, 80)
    assert torch.equal(codes, steps)  # kept frames are exact whatever the guesses
    assert all(kept == 1 for _, kept in passes[2:])
    long = [K for K, _ in passes if K > 1]
    assert len(long) <= 16 and len(passes) - len(long) >= 60, passes  # mostly steps


def test_a_pass_takes_fewer_guesses_than_frames(tiny_codetalker):

    model = tiny_codetalker()
    gen = FrameGenerator(model, model.style_vector(torch.tensor([0])))
    cross = model.cross_terms(model.audio_tokens(clip(3)[0], None, 3))
    with pytest.raises(ValueError, match="at most K - 1"):
        gen.block(cross, torch.zeros(1, 3, 4, dtype=torch.long))


def test_fast_generation_with_a_short_attention_window_runs_past_it(tiny_codetalker):
    from dataclasses import replace

    model = tiny_codetalker(vq_layers=0)
    model.cfg = replace(model.cfg, stage2=replace(model.cfg.stage2, attention_window=4))
    audio, _ = clip(15)
    out = model.generate(audio, torch.zeros(1, 20, 3), styles=torch.tensor([0]))
    assert out.shape == (1, 15, 20, 3) and torch.isfinite(out).all()
    model = tiny_codetalker(vq_layers=2)  # exact mode re-decodes the last 4 frames past the window
    model.cfg = replace(model.cfg, stage2=replace(model.cfg.stage2, attention_window=4))
    exact = model.generate(audio, torch.zeros(1, 20, 3), styles=torch.tensor([0]), mode="exact")
    assert exact.shape == (1, 15, 20, 3) and torch.isfinite(exact).all()


def test_whisper_encoder_behind_the_same_interface_and_releases_self_contained(
    tmp_path, tiny_codetalker
):
    transformers = pytest.importorskip("transformers")
    from dataclasses import replace

    tiny_whisper = dict(
        d_model=16,
        encoder_layers=1,
        encoder_attention_heads=2,
        encoder_ffn_dim=32,
        num_mel_bins=80,
        max_source_positions=1500,
    )
    source = tmp_path / "whisper"
    from transformers.models.whisper.modeling_whisper import WhisperEncoder

    WhisperEncoder(transformers.WhisperConfig(**tiny_whisper)).save_pretrained(source)
    base = tiny_codetalker()
    speech = SpeechEncoderConfig(kind="whisper", source=str(source), frozen=True)
    cfg = replace(base.cfg, stage2=replace(base.cfg.stage2, speech=speech))
    model = CodeTalker(cfg).eval()
    assert model.cfg.stage2.speech.source is None  # the release needs no path
    assert model.cfg.stage2.speech.hf_config["d_model"] == 16
    assert not any(p.requires_grad for p in model.speech.parameters())
    audio, verts = clip(9)
    out = model(audio, None, verts, torch.zeros(1, 20, 3), torch.tensor([0]))
    assert out.motion.shape == (1, 9, 60) and torch.isfinite(out.loss)
    path = save_model(model, tmp_path / "m.safetensors")
    source.rename(tmp_path / "gone")  # loading must not need the source directory
    again = load_model(path)
    a = model.generate(audio, torch.zeros(1, 20, 3), styles=torch.tensor([1]))
    torch.testing.assert_close(
        again.generate(audio, torch.zeros(1, 20, 3), styles=torch.tensor([1])), a
    )
    # int8 speech: Whisper's stem convolutions as Int8Conv1d (Whisper reads their strides)

    small = quantize_int8(model, speech=True, decoders=False)
    assert sum(isinstance(m, Int8Conv1d) for m in small.speech.modules()) == 2
    b = small.generate(audio, torch.zeros(1, 20, 3), styles=torch.tensor([1]))
    assert b.shape == a.shape and (b - a).abs().mean() < 0.1 * a.abs().mean()


def test_history_dropout_only_acts_in_training(tiny_codetalker):
    from dataclasses import replace

    model = tiny_codetalker()
    model.cfg = replace(model.cfg, stage2=replace(model.cfg.stage2, history_dropout=0.5))
    audio, verts = clip(12)
    args = (audio, None, verts, torch.zeros(1, 20, 3), torch.tensor([0]))
    with torch.no_grad():
        plain = model(*args).loss
        torch.testing.assert_close(model(*args).loss, plain)  # eval: deterministic, no dropout
        model.train()
        torch.manual_seed(1)
        assert not torch.allclose(model(*args).loss, plain)
    with pytest.raises(ValueError, match="history_dropout"):
        Stage2Config(styles=("a",), history_dropout=1.0)


def test_causal_vq_decoder_steps_equal_the_full_pass_and_ignore_later_codes(tiny_codetalker):
    model = tiny_codetalker(vq_layers=2, causal=True)
    dec = model.vqvae.decoder
    torch.manual_seed(1)
    z = torch.randn(2, 15, 4, 8)  # longer than the decoder's 6-frame attention window
    full = dec(z)
    later = z.clone()
    later[:, 9:] = torch.randn_like(later[:, 9:])
    torch.testing.assert_close(dec(later)[:, :9], full[:, :9])  # frames <= 8 ignore codes >= 9
    assert not torch.allclose(dec(later)[:, 9:], full[:, 9:])
    step = DecoderStep(dec)
    steps = torch.cat([dec.out(step.hidden(z[:, t : t + 1])) * dec.scale for t in range(15)], 1)
    torch.testing.assert_close(steps, full, atol=1e-5, rtol=1e-4)
    with pytest.raises(TalkmeshError, match="causal"):
        DecoderStep(tiny_codetalker().vqvae.decoder)
    with pytest.raises(ValueError, match="causal"):
        VQConfig(num_vertices=4, causal=True, instance_norm=True)


def test_fast_generation_equals_naive_with_a_causal_vq_decoder(tiny_codetalker):
    model = tiny_codetalker(vq_layers=2, causal=True)
    audio, _ = clip(14)
    templ = torch.randn(1, 20, 3)
    style = torch.tensor([1])
    fast = model.generate(audio, templ, styles=style, mode="fast")
    naive = model.generate(audio, templ, styles=style, mode="naive")
    torch.testing.assert_close(fast, naive, atol=1e-5, rtol=1e-4)


def test_exact_generation_equals_naive_with_the_papers_bidirectional_vq_decoder(tiny_codetalker):
    model = tiny_codetalker(
        vq_layers=2
    )  # bidirectional: fast mode's cached feedback is an approximation
    audio, _ = clip(15)
    templ = torch.randn(1, 20, 3)
    style = torch.tensor([1])
    naive = model.generate(audio, templ, styles=style, mode="naive")
    exact = model.generate(audio, templ, styles=style, mode="exact")
    fast = model.generate(audio, templ, styles=style, mode="fast")
    torch.testing.assert_close(exact, naive, atol=1e-5, rtol=1e-4)
    assert (fast - naive).abs().max() > 1e-3  # the model tells the feedbacks apart
    causal = tiny_codetalker(vq_layers=2, causal=True)  # exact there is fast mode, which is exact
    torch.testing.assert_close(
        causal.generate(audio, templ, styles=style, mode="exact"),
        causal.generate(audio, templ, styles=style, mode="fast"),
        atol=0,
        rtol=0,
    )
    with pytest.raises(TalkmeshError, match="fast, naive, exact"):
        model.generate(audio, templ, styles=style, mode="slow")


def test_self_feedback_feeds_back_the_models_own_teacher_forced_prediction(
    monkeypatch, tiny_codetalker
):
    from dataclasses import replace

    model = tiny_codetalker(causal=True)
    model.cfg = replace(model.cfg, stage2=replace(model.cfg.stage2, self_feedback=1.0))
    audio, verts = clip(12)
    args = (audio, None, verts, torch.zeros(1, 20, 3), torch.tensor([0]))
    fed = []
    original = model.motion_map.forward
    monkeypatch.setattr(model.motion_map, "forward", lambda x: fed.append(x) or original(x))
    with torch.no_grad():
        model(*args)
        assert len(fed) == 1  # eval: one teacher-forced pass
        model.train()
        out = model(*args)
    assert len(fed) == 3  # training: a first pass, then a pass on its own prediction
    scale = model.vqvae.decoder.scale
    first_prediction = fed[1] * scale  # what the first training pass fed back (the truth)...
    torch.testing.assert_close(first_prediction, verts.flatten(2)[:, :-1])
    assert not torch.allclose(fed[2] * scale, verts.flatten(2)[:, :-1])  # ...then its own motion
    assert torch.isfinite(out.loss)
    with pytest.raises(ValueError, match="self_feedback"):
        Stage2Config(styles=("a",), self_feedback=1.5)


def test_mel_lookahead_is_a_runtime_choice_within_the_trained_range():
    from talkmesh.models.speech import MelEncoder

    enc = MelEncoder(
        SpeechEncoderConfig(kind="mel", dim=8, lookahead_ms=0.0, lookahead_max_ms=100.0)
    )
    torch.nn.init.normal_(enc.shift_embedding.weight)
    enc.eval()
    audio = torch.randn(1, SR)
    enc.set_lookahead(0.0)
    early = enc(audio, None, 30)
    assert enc.lookahead_ms == 0.0
    enc.set_lookahead(100.0)
    late = enc(audio, None, 30)
    assert enc.lookahead_ms == 100.0 and not torch.allclose(early, late)
    with pytest.raises(TalkmeshError, match="trained for"):
        enc.set_lookahead(150.0)
    with pytest.raises(ValueError, match="lookahead_max_ms"):
        SpeechEncoderConfig(kind="whisper", lookahead_max_ms=100.0)


@pytest.mark.parametrize("causal", [False, True])
def test_the_conv_step_is_the_convolutions_last_frame(causal, tiny_codetalker):
    conv = tiny_codetalker(causal=causal).vqvae.decoder.conv
    x = torch.randn(2, 5, conv.conv.in_channels)
    full = conv(x)  # replicate padding: causal (4, 0), centred (2, 2)
    # the last frame sees x0..x4 (causal) or x2, x3, x4 and x4 twice more (the right padding)
    window = x if causal else torch.cat([x[:, 2:], x[:, 4:].expand(-1, 2, -1)], dim=1)
    torch.testing.assert_close(conv.step(window.transpose(1, 2)[:, None]), full[:, -1:])


@pytest.mark.parametrize("causal", [False, True])
def test_int8_generation_stays_close_to_float32_and_leaves_the_model_alone(causal, tiny_codetalker):
    model = tiny_codetalker(vq_layers=2, causal=causal)
    before = {k: v.clone() for k, v in model.state_dict().items()}
    audio, _ = clip(14)
    templ = torch.zeros(1, 20, 3)
    style = torch.tensor([1])
    small = quantize_int8(model)
    assert small.vqvae.decoder.conv.linear is not None and small.int8
    fp32 = model.generate(audio, templ, styles=style)
    int8 = small.generate(audio, templ, styles=style)
    assert int8.shape == fp32.shape and torch.isfinite(int8).all()
    assert (int8 - fp32).abs().mean() < 0.1 * fp32.abs().mean()  # close, not equal
    assert all(torch.equal(v, model.state_dict()[k]) for k, v in before.items())
    assert not hasattr(model, "int8") and model.vqvae.decoder.conv.linear is None

    def quantized(module):
        return any(isinstance(m, Int8Linear) for m in module.modules())

    fold = FrameGenerator(small, small.style_vector(style)).fold
    for part in (
        small.blocks,
        small.feat_map,
        small.vqvae.decoder.blocks,
        small.vqvae.decoder.inp,
        small.vqvae.decoder.mid,
        small.vqvae.decoder.conv.linear,
        fold,
    ):
        assert quantized(part)
    w2v = tiny_codetalker(
        vq_layers=2, speech="wav2vec2", causal=causal
    )  # a speech encoder with linears
    assert not quantized(quantize_int8(w2v).speech)
    both = quantize_int8(w2v, speech=True)  # the speech encoder's linear layers as well
    assert quantized(both.speech) and not quantized(w2v.speech)
    speech_only = quantize_int8(w2v, speech=True, decoders=False)
    assert quantized(speech_only.speech) and not quantized(speech_only.blocks)
    assert not getattr(speech_only, "int8", False)  # its feedback map stays float32 too
    ref = w2v.generate(audio, templ, styles=style)
    out = both.generate(audio, templ, styles=style)
    assert (out - ref).abs().mean() < 0.1 * ref.abs().mean()


def test_int8_linear_rows_do_not_depend_on_each_other():
    torch.manual_seed(0)
    linear = torch.nn.Linear(37, 11)  # odd sizes on purpose
    q = Int8Linear(linear.weight, linear.bias)
    x = torch.randn(2, 9, 37)
    x[0, 3] *= 100  # a row with a large range must not change the others' scale
    together = q(x)
    alone = torch.stack([torch.cat([q(x[b, t : t + 1]) for t in range(9)]) for b in range(2)])
    assert torch.equal(together, alone)  # bitwise: integer sums, one scale per row
    ref = linear(x)
    assert (together - ref).abs().max() < 0.02 * ref.abs().max()
    assert q(x[:, :0]).shape == (2, 0, 11)


@pytest.mark.parametrize("stride,padding", [(1, 0), (2, 1), (5, 0)])
def test_int8_conv1d_is_the_convolution_in_int8(stride, padding):

    torch.manual_seed(0)
    conv = torch.nn.Conv1d(6, 10, 3, stride=stride, padding=padding)
    q = int8_layers(torch.nn.Sequential(conv))[0]
    assert isinstance(q, Int8Conv1d)
    x = torch.randn(2, 6, 23)
    ref, out = conv(x), q(x)
    assert out.shape == ref.shape
    assert (out - ref).abs().max() < 0.02 * ref.abs().max()
    # each output frame is its own row: the frames outside its window do not change it
    y = x.clone()
    y[:, :, -1] *= 50
    first = (ref.shape[-1] - 1) * stride - padding  # the first input the last window reads
    assert torch.equal(q(y)[..., : first // stride], out[..., : first // stride])
    grouped = torch.nn.Conv1d(6, 6, 3, groups=2)  # not a plain convolution: left as it is
    assert int8_layers(torch.nn.Sequential(grouped))[0] is grouped


@pytest.mark.parametrize("causal", [False, True])
def test_int8_passes_give_the_codes_of_one_frame_at_a_time(causal, tiny_codetalker):

    model = quantize_int8(tiny_codetalker(vq_layers=2, causal=causal))
    audio, _ = clip(30)
    templ, style = torch.zeros(1, 20, 3), torch.tensor([1])
    calls = []
    block = FrameGenerator.block

    def counted(self, cross, drafts):
        calls.append(cross[0].shape[1])
        return block(self, cross, drafts)

    FrameGenerator.block = counted
    try:
        steps = model.generate(audio, templ, styles=style, block=1)
        calls.clear()
        passes = model.generate(audio, templ, styles=style)
    finally:
        FrameGenerator.block = block
    assert max(calls) > 1 and len(calls) < steps.shape[1]  # passes ran, several frames each
    torch.testing.assert_close(passes, steps, atol=1e-5, rtol=1e-4)


def test_the_folded_feedback_map_is_kept_until_its_weights_change(tiny_codetalker):

    model = tiny_codetalker(vq_layers=2, causal=True)
    audio, _ = clip(10)
    templ, style = torch.zeros(1, 20, 3), torch.tensor([1])
    first = model.generate(audio, templ, styles=style)
    fold = FrameGenerator(model, model.style_vector(style)).fold
    assert FrameGenerator(model, model.style_vector(style)).fold is fold  # built once
    x = torch.randn(3, model.cfg.vq.hidden)
    want = model.motion_map(model.vqvae.decoder.out(x))
    torch.testing.assert_close(fold(x), want, atol=1e-5, rtol=1e-4)
    with torch.no_grad():
        # an update in place (as an optimiser step), big enough to change the tiny model's codes
        model.motion_map.weight.mul_(100.0)
    again = FrameGenerator(model, model.style_vector(style)).fold
    assert again is not fold
    torch.testing.assert_close(again(x), model.motion_map(model.vqvae.decoder.out(x)))
    fast = model.generate(audio, templ, styles=style)
    assert not torch.allclose(fast, first)
    torch.testing.assert_close(
        fast, model.generate(audio, templ, styles=style, mode="naive"), atol=1e-5, rtol=1e-4
    )
    assert "_folded" not in "".join(model.state_dict())


def test_the_multilingual_streaming_recipe_trains_on_the_bundled_models_motion_stage():
    pytest.importorskip("yaml")
    from talkmesh.config import to_dict
    from talkmesh.models.release import load_model
    from talkmesh.training.codetalker import build_config
    from talkmesh.training.trainer import DatasetInfo, _init_path, load_recipe

    recipe = load_recipe(CONFIGS / "codetalker_stream_multilingual.yaml")
    assert recipe.task == "codetalker-stage2" and recipe.model["head_pairs"] == 8
    bundled = load_model(_init_path(recipe.init))
    info = DatasetInfo(num_vertices=bundled.num_vertices, motion_fps=30.0, train_subjects=("a",))
    model = {k: v for k, v in recipe.model.items() if k != "head_pairs"}
    cfg = build_config(model, info)
    assert to_dict(cfg.vq) == to_dict(bundled.cfg.vq)  # _build_stage2 takes its VQ-VAE
    assert cfg.vq.causal and cfg.stage2.speech.kind == "mel"
    assert recipe.train.lip_gap_weight > 0 and recipe.data.augment.enabled
    assert recipe.train.lip_close_weight > 0 and recipe.warm_start == recipe.init
    assert bundled.decoder_head is not None  # its face term comes with it (with_source_face)
