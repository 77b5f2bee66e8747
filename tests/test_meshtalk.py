"""MeshTalk: expression space, losses, the autoregressive prior and its cached sampler (tiny configs)."""

from __future__ import annotations

import json

import pytest
import torch

from talkmesh.config import from_dict, to_dict
from talkmesh.errors import TalkmeshError
from talkmesh.models.mel import MelAudioEncoder, MelConfig
from talkmesh.models.meshtalk.model import (
    MeshTalk,
    MeshTalkConfig,
    MeshTalkForward,
    gumbel_one_hot,
    meshtalk_config,
    meshtalk_loss,
)
from talkmesh.models.meshtalk.prior import AutoregressivePrior, PriorConfig, prior_config

V, H, C = 30, 4, 8
FPS = 30.0
SR = 16_000
TINY_AUDIO = MelConfig(width=16, out_dim=16)


def tiny_config(**kw) -> MeshTalkConfig:
    base = dict(
        num_vertices=V,
        fps=FPS,
        num_heads=H,
        num_classes=C,
        audio=TINY_AUDIO,
        expression_widths=(32, 16, 16),
        fusion_width=32,
        decoder_widths=(32, 16, 16),
    )
    base.update(kw)
    return MeshTalkConfig(**base)


def tiny_prior(**kw) -> AutoregressivePrior:
    base = dict(num_heads=H, num_classes=C, width=16, audio=TINY_AUDIO, fps=FPS)
    base.update(kw)
    return AutoregressivePrior(PriorConfig(**base)).eval()


def regions():
    mouth = torch.zeros(V)
    mouth[:10] = 1.0
    mouth[10:15] = 0.5
    upper = 1.0 - mouth
    eyelids = torch.tensor([20, 21, 22])
    return mouth, upper, eyelids


def tiny_model(seed: int = 0) -> MeshTalk:
    torch.manual_seed(seed)
    model = MeshTalk(tiny_config(), *regions())
    torch.nn.init.normal_(model.decoder.output.weight, std=0.1)  # untrained: not the bare template
    return model.eval()


def tiny_data(B: int = 2, T: int = 12, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    templates = torch.randn(B, V, 3, generator=g)
    vertices = templates[:, None] + 0.1 * torch.randn(B, T, V, 3, generator=g)
    audio = 0.1 * torch.randn(B, int(T * SR / FPS), generator=g)
    return vertices, templates, audio


# ---------------------------------------------------------------------------------------------
# configs and audio encoder


def test_presets_have_the_paper_and_released_sizes():
    assert (meshtalk_config("paper", V).num_heads, meshtalk_config("paper", V).num_classes) == (
        64,
        128,
    )
    assert (
        meshtalk_config("released", V).num_heads,
        meshtalk_config("released", V).num_classes,
    ) == (16, 128)
    for preset in ("paper", "released", "small"):
        m, p = meshtalk_config(preset, V), prior_config(preset)
        assert (m.num_heads, m.num_classes) == (p.num_heads, p.num_classes)
    audio = MelConfig()  # 600 ms snippet: 500 ms before, 100 ms after (paper Sec. 4)
    assert (audio.receptive_field, audio.context_frames, audio.lookahead_frames) == (61, 50, 10)
    assert PriorConfig().receptive_field == 16
    with pytest.raises(TalkmeshError):
        meshtalk_config("huge", V)
    with pytest.raises(TalkmeshError, match="lookahead"):
        MelConfig(lookahead_ms=1000.0)


def test_audio_window_is_exactly_context_plus_lookahead():
    torch.manual_seed(0)
    cfg = MelConfig(width=16, out_dim=16, lookahead_ms=100.0)
    enc = MelAudioEncoder(cfg, FPS).eval().double()  # float64: "unchanged" means equal to 1e-12
    T, t = 40, 25
    audio = 0.1 * torch.randn(1, int(T * SR / FPS), dtype=torch.float64)
    base = enc(audio, None, T)
    assert base.shape == (1, T, 16)
    half_window = cfg.win_length // 2  # the STFT window around each mel frame's centre
    centre = int(enc.frame_indices(T)[t]) * cfg.hop_length
    after = audio.clone()  # change everything after frame t's look-ahead (+ half an STFT window)
    after[:, centre + cfg.lookahead_frames * cfg.hop_length + half_window + 1 :] += 0.5
    out = enc(after, None, T)
    assert torch.allclose(out[:, : t + 1], base[:, : t + 1], rtol=0, atol=1e-12)
    assert (out[:, t + 1 :] - base[:, t + 1 :]).abs().amax(-1).min() > 1e-6
    before = audio.clone()  # change everything before frame t's context
    first_seen = centre - cfg.context_frames * cfg.hop_length - half_window
    assert first_seen > 0
    before[:, :first_seen] += 0.5
    out = enc(before, None, T)
    assert torch.allclose(out[:, t:], base[:, t:], rtol=0, atol=1e-12)
    assert (out[:, t - 1] - base[:, t - 1]).abs().max() > 1e-6


def test_gumbel_is_hard_one_hot_with_straight_through_gradient():
    logits = torch.randn(2, 3, H, C, requires_grad=True)
    g = torch.Generator().manual_seed(0)
    q = gumbel_one_hot(logits, tau=1.0, sample=True, generator=g)
    assert set(q.one_hot.detach().unique().tolist()) <= {0.0, 1.0}
    assert torch.equal(q.one_hot.argmax(-1), q.codes)
    (q.one_hot * torch.randn_like(q.one_hot)).sum().backward()
    assert logits.grad is not None and logits.grad.abs().sum() > 0
    det = gumbel_one_hot(logits, tau=1.0, sample=False)
    assert torch.equal(det.codes, logits.argmax(-1))


# ---------------------------------------------------------------------------------------------
# expression space


def test_forward_shapes_and_losses_use_the_region_maps():
    model = tiny_model()
    model.train()
    vertices, templates, audio = tiny_data()
    out = model(vertices, templates, audio, generator=torch.Generator().manual_seed(0))
    assert out.reconstruction.shape == out.audio_driven.shape == vertices.shape
    assert out.quantized.codes.shape == (2, 12, H)
    loss = model.loss(out, vertices)
    assert loss.total.requires_grad and torch.isfinite(loss.total)
    loss.total.backward()
    assert model.fusion.layers[0].weight.grad.abs().sum() > 0  # gradient reaches the encoder

    # an error on mouth-only vertices moves the mouth term, not the upper-face term
    mouth, upper, eyelid_ids = regions()
    eyelid = torch.zeros(V)
    eyelid[eyelid_ids] = 1
    target = vertices
    bad = target.clone()
    bad[:, :, :10] += 1.0
    fwd = MeshTalkForward(bad, bad, bad, out.quantized)
    terms = meshtalk_loss(fwd, target, mouth, upper, eyelid)
    assert terms.mouth > 0 and terms.upper == 0 and terms.eyelid == 0 and terms.reconstruction > 0
    mask = torch.zeros(2, 12, dtype=torch.bool)  # padded frames do not count
    mask[:, :6] = True
    bad_late = target.clone()
    bad_late[:, 6:, 20] += 1.0
    terms = meshtalk_loss(
        MeshTalkForward(bad_late, bad_late, bad_late, out.quantized),
        target,
        mouth,
        upper,
        eyelid,
        mask,
    )
    assert terms.total == 0


def test_padded_batch_equals_single_samples():
    model = tiny_model()
    vertices, templates, audio = tiny_data(B=2, T=12)
    short_T, short_S = 7, int(7 * SR / FPS)
    vertices[1, short_T:] = 0
    audio[1, short_S:] = 0
    lengths = torch.tensor([audio.shape[1], short_S])
    batch = model.encode(vertices, templates, audio, lengths)
    single = model.encode(vertices[1:, :short_T], templates[1:], audio[1:, :short_S])
    assert torch.allclose(batch.logits[1, :short_T], single.logits[0], atol=1e-5)
    dec = model.decode(templates, batch.codes)
    assert torch.allclose(dec[1, :short_T], model.decode(templates[1:], single.codes)[0], atol=1e-5)


def test_decoder_animates_any_template_and_codes_round_trip():
    model = tiny_model()
    vertices, templates, audio = tiny_data()
    q = model.encode(vertices, templates, audio)
    from_ids = model.decode(templates, q.codes)
    assert torch.allclose(from_ids, model.decode(templates, q.one_hot))
    shifted = model.decode(templates + 1.0, q.codes)
    assert shifted.shape == (2, 12, V, 3)
    assert not torch.allclose(
        shifted, from_ids + 1.0, atol=1e-3
    )  # the template is an input, not an offset
    model.decoder.output.weight.data.zero_()
    model.decoder.output.bias.data.zero_()
    assert torch.allclose(model.decode(templates, q.codes), templates[:, None].expand_as(vertices))


def test_retarget_and_dub():
    model = tiny_model()
    vertices, templates, audio = tiny_data()
    _, other_templates, new_audio = tiny_data(seed=1)
    moved = model.retarget(vertices, templates, audio, other_templates)
    codes = model.encode(vertices, templates, audio).codes
    assert torch.allclose(moved, model.decode(other_templates, codes))
    assert not torch.allclose(moved, model.decode(templates, codes))
    # same template: re-targeting is the reconstruction
    assert torch.allclose(
        model.retarget(vertices, templates, audio, templates),
        model(vertices, templates, audio).reconstruction,
    )

    dubbed = model.dub(vertices, templates, new_audio)
    assert dubbed.shape == vertices.shape
    assert torch.allclose(
        dubbed, model.decode(templates, model.encode(vertices, templates, new_audio).codes)
    )
    assert torch.allclose(
        model.dub(vertices, templates, audio), model.retarget(vertices, templates, audio, templates)
    )
    # both inputs reach the code: the original animation and the new audio
    expr_logits = model.encode(vertices, templates, new_audio).logits
    other_expr = model.encode(tiny_data(seed=2)[0], templates, new_audio).logits
    assert (expr_logits - other_expr).abs().max() > 1e-4
    assert (expr_logits - model.encode(vertices, templates, audio).logits).abs().max() > 1e-4


def test_training_steps_reduce_the_loss():
    torch.manual_seed(0)
    model = MeshTalk(tiny_config(), *regions())
    g = torch.Generator().manual_seed(0)
    templates = torch.randn(2, V, 3, generator=g)
    t = torch.arange(10.0)[None, :, None, None]
    patterns = torch.randn(2, 1, V, 3, generator=g)
    vertices = templates[:, None] + 0.1 * torch.sin(0.7 * t) * patterns  # structured motion
    audio = 0.1 * torch.randn(2, int(10 * SR / FPS), generator=g)
    model.set_statistics(templates, vertices - templates[:, None])
    opt = torch.optim.Adam(model.parameters(), lr=1e-2)
    model.train()
    losses = []
    for step in range(40):
        loss = model.loss(
            model(vertices, templates, audio, generator=torch.Generator().manual_seed(step)),
            vertices,
        )
        opt.zero_grad()
        loss.total.backward()
        opt.step()
        losses.append(loss.total.item())
    assert losses[-1] < 0.5 * losses[0]


def test_bad_inputs_raise_one_line_errors():
    model = tiny_model()
    vertices, templates, audio = tiny_data()
    with pytest.raises(TalkmeshError, match="V=30"):
        model.encode(vertices[:, :, :20], templates, audio)
    with pytest.raises(TalkmeshError, match="codes"):
        model.decode(templates, torch.full((2, 3, H), C))
    with pytest.raises(TalkmeshError, match="region maps"):
        MeshTalk(tiny_config(), mouth_weight=torch.ones(V + 1))
    with pytest.raises(TalkmeshError, match="eyelid"):
        MeshTalk(tiny_config(), eyelids=torch.tensor([V]))
    prior = tiny_prior()
    with pytest.raises(TalkmeshError, match="temperature"):
        prior.sample(torch.zeros(1, 3, 16), temperature=0.0)
    with pytest.raises(TalkmeshError, match="audio features"):
        prior.sample(torch.zeros(1, 3, 15))


def test_save_load_round_trip():
    model = tiny_model()
    model.set_statistics(torch.randn(4, V, 3), 0.01 * torch.randn(4, 5, V, 3))
    model.audio_encoder.set_statistics(0.1 * torch.randn(2, SR))
    assert model.audio_encoder.mel_std.min() < 3.0  # no longer the defaults
    prior = tiny_prior()
    for module, cls in ((model, MeshTalkConfig), (prior, PriorConfig)):
        blob = json.dumps(to_dict(module.config))
        state = {k: v.clone() for k, v in module.state_dict().items()}
        rebuilt = type(module)(from_dict(cls, json.loads(blob)))
        rebuilt.load_state_dict(state, strict=True)
        assert rebuilt.config == module.config
        for k, v in rebuilt.state_dict().items():
            assert torch.equal(v, state[k]), k
    rebuilt_model = MeshTalk(from_dict(MeshTalkConfig, to_dict(model.config)))
    rebuilt_model.load_state_dict(model.state_dict(), strict=True)
    assert torch.equal(
        rebuilt_model.eyelid_mask, model.eyelid_mask
    )  # region maps travel with the weights
    vertices, templates, audio = tiny_data()
    assert torch.equal(
        rebuilt_model.eval().retarget(vertices, templates, audio, templates),
        model.retarget(vertices, templates, audio, templates),
    )


# ---------------------------------------------------------------------------------------------
# autoregressive prior


def test_prior_masking():
    torch.manual_seed(0)
    prior = tiny_prior().double()
    B, T = 1, 20
    codes = torch.randint(0, C, (B, T, H))
    audio = torch.randn(B, T, 16, dtype=torch.float64)
    base = prior(codes, audio)
    assert base.shape == (B, T, H, C)
    for t, h in [(0, 0), (5, 2), (12, 3), (19, 1)]:
        changed = codes.clone()
        changed[0, t, h] = (codes[0, t, h] + 1) % C
        out = prior(changed, audio)
        diff = (out - base).abs().amax(-1)[0]  # (T, H)
        assert diff[:t].max() == 0 if t else True  # earlier frames: untouched
        assert diff[t, : h + 1].max() == 0  # this frame, heads up to and including h
        later = torch.cat([diff[t, h + 1 :], diff[t + 1 :].flatten()])
        if later.numel():
            assert later.max() > 0  # and it is used by what comes after
    changed_audio = audio.clone()
    changed_audio[0, 10:] += 1.0  # audio features are per frame: frame 10 on
    diff = (prior(codes, changed_audio) - base).abs().amax((-1, -2))[0]
    assert diff[:10].max() == 0 and diff[10:].min() > 0


def test_prior_receptive_field():
    torch.manual_seed(0)
    prior = tiny_prior().double()
    codes = torch.randint(0, C, (1, 40, H))
    audio = torch.randn(1, 40, 16, dtype=torch.float64)
    base = prior(codes, audio)
    changed = codes.clone()
    changed[0, 5] = (codes[0, 5] + 1) % C
    diff = (prior(changed, audio) - base).abs().amax((-1, -2))[0]
    R = prior.config.receptive_field
    assert diff[5 + R - 1] > 0 and diff[5 + R :].max() == 0


@pytest.mark.parametrize(
    "kwargs",
    [dict(temperature=1.0), dict(temperature=0.7, top_k=3), dict(argmax=True)],
)
def test_cached_sampling_equals_uncached(kwargs):
    torch.manual_seed(0)
    prior = tiny_prior().double()
    audio = torch.randn(2, 24, 16, dtype=torch.float64)
    cached = prior.sample(audio, generator=torch.Generator().manual_seed(3), **kwargs)
    uncached = prior.sample_uncached(audio, generator=torch.Generator().manual_seed(3), **kwargs)
    assert cached.shape == (2, 24, H)
    assert torch.equal(cached, uncached)
    if "top_k" in kwargs:  # every draw is among the k most likely under the teacher-forced model
        with torch.no_grad():
            logits = prior(cached, audio)
        rank = (logits > logits.gather(-1, cached[..., None])).sum(-1)
        assert rank.max() < kwargs["top_k"]
    if kwargs.get("argmax"):
        with torch.no_grad():
            assert torch.equal(prior(cached, audio).argmax(-1), cached)
    again = prior.sample(audio, generator=torch.Generator().manual_seed(3), **kwargs)
    assert torch.equal(again, cached)


def test_prompt_prefill_matches_uncached():
    torch.manual_seed(0)
    prior = tiny_prior().double()
    audio = torch.randn(1, 30, 16, dtype=torch.float64)
    prompt = torch.randint(0, C, (1, 20, H))
    cached = prior.sample(audio, prompt=prompt, generator=torch.Generator().manual_seed(1))
    uncached = prior.sample_uncached(
        audio, prompt=prompt, generator=torch.Generator().manual_seed(1)
    )
    assert torch.equal(cached[:, :20], prompt)
    assert torch.equal(cached, uncached)


def test_perplexity_is_eq9():
    torch.manual_seed(0)
    prior = tiny_prior()
    codes = torch.randint(0, C, (2, 9, H))
    audio = torch.randn(2, 9, 16)
    logp = torch.log_softmax(prior(codes, audio), -1).gather(-1, codes[..., None])
    expected = torch.exp(-logp.sum() / logp.numel())
    assert torch.allclose(prior.perplexity(codes, audio), expected, rtol=1e-5)
    mask = torch.ones(2, 9, dtype=torch.bool)
    mask[1, 4:] = False
    logp_valid = torch.cat([logp[0].flatten(), logp[1, :4].flatten()])
    assert torch.allclose(
        prior.perplexity(codes, audio, mask), torch.exp(-logp_valid.mean()), rtol=1e-5
    )
    assert 1.0 < float(prior.perplexity(codes, audio)) < 4 * C  # untrained: near uniform


def test_prior_learns_with_teacher_forcing():
    torch.manual_seed(0)
    prior = tiny_prior().train()
    codes = torch.randint(0, C, (2, 16, H))
    codes[:, 1:] = codes[:, :1]  # a constant sequence: predictable from the past
    raw = 0.1 * torch.randn(2, int(16 * SR / FPS))
    opt = torch.optim.Adam(prior.parameters(), lr=1e-2)
    first = None
    for _ in range(40):
        loss = prior.loss(codes, prior.audio_features(raw, None, 16))
        first = first if first is not None else loss.perplexity.item()
        opt.zero_grad()
        loss.loss.backward()
        opt.step()
    assert loss.perplexity.item() < 0.5 * first


# ---------------------------------------------------------------------------------------------
# the release: expression space + prior behind the common model surface


def tiny_release(prior: bool = True):
    from talkmesh.models.meshtalk.model import MeshTalkModel, MeshTalkModelConfig

    torch.manual_seed(0)
    cfg = MeshTalkModelConfig(
        tiny_config(),
        PriorConfig(num_heads=H, num_classes=C, width=16, audio=TINY_AUDIO, fps=FPS)
        if prior
        else None,
    )
    net = MeshTalkModel(cfg, regions())
    torch.nn.init.normal_(net.model.decoder.output.weight, std=0.1)
    return net.eval()


def test_release_round_trip_and_seeded_sampling(tmp_path):
    from talkmesh.models.release import load_model, save_model

    net = tiny_release()
    assert net.family == "meshtalk" and net.styles == () and net.num_vertices == V
    save_model(net, tmp_path / "mt.safetensors")
    loaded = load_model(tmp_path / "mt.safetensors")
    assert type(loaded) is type(net) and loaded.cfg == net.cfg
    assert torch.equal(loaded.model.eyelid_mask, net.model.eyelid_mask)
    _, templates, audio = tiny_data(B=1, T=20)
    a = net.generate(audio, templates, seed=3)
    assert a.shape == (1, 20, V, 3)
    assert torch.equal(a, loaded.generate(audio, templates, seed=3))  # same weights, same draws
    assert torch.equal(a, net.generate(audio, templates, seed=3))
    assert not torch.equal(a, net.generate(audio, templates, seed=4))  # sampling: seeds differ
    greedy = net.generate(audio, templates, seed=3, argmax=True)
    assert torch.equal(greedy, net.generate(audio, templates, seed=4, argmax=True))
    # the reference sampler that recomputes the whole history draws the same codes
    assert torch.equal(
        net.sample_codes(audio, seed=5), net.sample_codes(audio, seed=5, cached=False)
    )


def test_release_errors():
    _, templates, audio = tiny_data(B=1, T=10)
    with pytest.raises(TalkmeshError, match="no prior"):
        tiny_release(prior=False).generate(audio, templates)
    with pytest.raises(TalkmeshError, match="no speaker styles"):
        tiny_release().generate(audio, templates, style_weights=torch.ones(1, 2))
    with pytest.raises(TalkmeshError, match=f"V={V}"):
        tiny_release().generate(audio, templates[:, :-1])
    from talkmesh.models.meshtalk.model import MeshTalkModelConfig

    with pytest.raises(TalkmeshError, match="must match"):
        MeshTalkModelConfig(tiny_config(), PriorConfig(num_heads=H + 1, num_classes=C))


def test_logit_norm_bounds_the_softmax():
    torch.manual_seed(0)
    model = MeshTalk(tiny_config(logit_norm=True), *regions())
    with torch.no_grad():
        model.fusion.layers[-1].weight.mul_(1e4)  # raw logits would saturate the softmax
    vertices, templates, audio = tiny_data()
    with torch.no_grad():
        aud, expr = model.features(vertices, templates, audio, None)
        q = model.quantize(aud, expr, sample=False)
    assert torch.allclose(q.logits.mean(-1), torch.zeros(()), atol=1e-4)
    # largest possible standardised logit gap over C classes keeps p_max well below 1
    assert float(q.logits.softmax(-1).amax(-1).max()) < 0.99
    raw = MeshTalk(tiny_config(), *regions())
    raw.load_state_dict(model.state_dict())
    with torch.no_grad():
        p_raw = raw.quantize(aud, expr, sample=False).logits.softmax(-1).amax(-1)
    assert float(p_raw.mean()) > 0.95


def test_expression_only_inputs_ignore_the_audio():
    torch.manual_seed(0)
    model = MeshTalk(tiny_config(inputs="expression"), *regions()).eval()
    vertices, templates, audio = tiny_data()
    a = model.encode(vertices, templates, audio).logits
    b = model.encode(vertices, templates, torch.randn_like(audio)).logits
    assert torch.equal(a, b)
    both = MeshTalk(tiny_config(), *regions()).eval()
    both.load_state_dict(model.state_dict())
    assert not torch.equal(
        both.encode(vertices, templates, audio).logits,
        both.encode(vertices, templates, torch.randn_like(audio)).logits,
    )
    with pytest.raises(TalkmeshError, match="inputs"):
        tiny_config(inputs="audio")


def test_talkmesh_speech_encoder_and_a_prior_on_the_expression_spaces_audio(tmp_path):
    from talkmesh.models.meshtalk.model import MeshTalkModel, MeshTalkModelConfig
    from talkmesh.models.release import load_model, save_model
    from talkmesh.models.speech import SpeechEncoderConfig

    torch.manual_seed(0)
    speech = SpeechEncoderConfig(kind="mel", dim=16, frame_rate=FPS)
    prior = PriorConfig(
        num_heads=H, num_classes=C, width=16, audio=TINY_AUDIO, fps=FPS, audio_source="expression"
    )
    net = MeshTalkModel(MeshTalkModelConfig(tiny_config(speech=speech), prior), regions()).eval()
    assert net.prior.audio_encoder is None  # no second audio encoder
    _, templates, audio = tiny_data(B=1, T=15)
    feats = net.audio_features(audio, None, 15)
    torch.testing.assert_close(feats, net.model.audio_encoder(audio, None, 15))
    assert feats.shape == (1, 15, TINY_AUDIO.out_dim)
    save_model(net, tmp_path / "m.safetensors")
    loaded = load_model(tmp_path / "m.safetensors")
    assert torch.equal(
        loaded.generate(audio, templates, seed=1), net.generate(audio, templates, seed=1)
    )
    with pytest.raises(TalkmeshError, match="audio_source"):
        net.prior.audio_features(audio, None, 15)
    with pytest.raises(TalkmeshError, match="out_dim"):
        MeshTalkModelConfig(
            tiny_config(), PriorConfig(num_heads=H, num_classes=C, audio_source="expression")
        )


@pytest.mark.parametrize(
    "name, heads, classes",
    [("meshtalk_synth", 8, 32), ("meshtalk_paper", 64, 128), ("meshtalk_released", 16, 128)],
)
def test_recipes_have_both_stages_and_the_preset_sizes(name, heads, classes):
    from pathlib import Path

    from talkmesh.training.meshtalk import _config
    from talkmesh.training.trainer import load_recipes

    path = Path(__file__).resolve().parents[1] / "configs" / f"{name}.yaml"
    stages = load_recipes(path, ["train.seed=4"])
    assert [r.task for _, r in stages] == ["meshtalk", "meshtalk-prior"]
    assert all(r.train.seed == 4 for _, r in stages)
    assert stages[1][1].init == f"{stages[0][1].train.out_dir}/model.safetensors"
    model = {k: v for k, v in stages[0][1].model.items() if k != "speech"}  # no Whisper files
    cfg = _config(MeshTalkConfig, meshtalk_config, model, 50, 30.0)
    prior_model = {k: v for k, v in stages[1][1].model.items() if k != "sampling"}  # the release's
    prior = _config(PriorConfig, prior_config, prior_model, 30.0)
    assert (
        (cfg.num_heads, cfg.num_classes) == (prior.num_heads, prior.num_classes) == (heads, classes)
    )
