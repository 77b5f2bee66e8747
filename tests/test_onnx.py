"""ONNX export (talkmesh export-onnx) and generation with ONNX Runtime against PyTorch."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import onnx
import pytest
import torch
from conftest import build_tiny_codetalker
from fixtures import TINY_WHISPER

from talkmesh.audio.loading import load_audio
from talkmesh.cli import main
from talkmesh.errors import TalkmeshError
from talkmesh.models.onnx import OnnxModel, export_onnx, speech_path
from talkmesh.models.release import load_model
from talkmesh.models.speech import SpeechEncoderConfig

CLIP = Path(
    "/usr/share/pocketsphinx/test/data/librivox/sense_and_sensibility_01_austen_64kb-0880.wav"
)  # 3.0 s of speech
TOLERANCE = 1e-4  # of the motion's scale (its largest offset)


def tiny_model(**options):
    speech = SpeechEncoderConfig(kind="whisper", dim=16, hf_config=TINY_WHISPER)
    return build_tiny_codetalker(speech=speech, causal=True, attention_window=7, **options)


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    model = tiny_model()
    path = tmp_path_factory.mktemp("onnx") / "tiny.onnx"
    assert export_onnx(model, path) == [path, speech_path(path)]
    return model, path


@pytest.fixture(scope="module")
def speech() -> torch.Tensor:
    return torch.from_numpy(load_audio(CLIP))[None]


def test_onnx_runtime_generates_what_pytorch_generates(exported, speech):
    model, path = exported
    onnx_model = load_model(path)
    assert isinstance(onnx_model, OnnxModel)
    assert (onnx_model.styles, onnx_model.motion_fps) == (model.styles, model.motion_fps)
    template = torch.randn(1, model.num_vertices, 3) * 0.1
    weights = torch.tensor([[0.7, 0.3]])
    want = model.generate(speech, template, style_weights=weights)
    got = onnx_model.generate(speech, template, style_weights=weights)
    assert got.shape == want.shape == (1, 90, model.num_vertices, 3)
    scale = (want - template[:, None]).abs().max()
    assert scale > 0.01  # the frames move: equality is not of two rests
    assert (got - want).abs().max() <= TOLERANCE * scale
    chunks = list(onnx_model.generate_chunks(speech, template, style_weights=weights, chunk=32))
    assert [c.shape[1] for c in chunks] == [32, 32, 26]
    assert torch.equal(torch.cat(chunks, 1), got)


def test_animate_a_file_with_an_onnx_model(exported, speech):
    """``animate`` on a file with an .onnx model (the path `talkmesh animate --model x.onnx`
    takes): it hears the polyphase 16 kHz audio PyTorch hears, the same motion."""
    from talkmesh.face.assets import plain_head
    from talkmesh.pipeline import animate

    model, path = exported
    rng = np.random.default_rng(0)
    head = plain_head(rng.normal(size=(model.num_vertices, 3)) * 0.1, np.array([[0, 1, 2]]), "t")
    got = animate(str(CLIP), model=load_model(path), head=head, style_mix={"a": 1.0})
    want = animate(str(CLIP), model=model, head=head, style_mix={"a": 1.0})
    scale = np.abs(want.vertices - head.template).max()
    assert scale > 0.01 and np.abs(got.vertices - want.vertices).max() <= TOLERANCE * scale


def test_streams_batched_in_one_step_equal_each_alone(exported):
    model, path = exported
    onnx_model = OnnxModel(path)
    rng = np.random.default_rng(0)
    B, T = 3, 12  # three streams, started at frames 0, 2 and 5
    feats = rng.normal(size=(B, T, model.audio_map.in_features)).astype(np.float32)
    style = onnx_model.style(None).repeat(B, 0)

    def alone(b: int) -> list[np.ndarray]:
        state, out = onnx_model.start(style[b : b + 1]), []
        for t in range(T):
            motion, state = onnx_model.step_frames(
                feats[b, t][None], np.array([t]), style[:1], state
            )
            out.append(motion[0])
        return out

    want = [alone(b) for b in range(B)]
    starts = [0, 2, 5]
    state = onnx_model.start(style)
    for tick in range(T + 5):
        t = np.array([max(0, min(tick - s, T - 1)) for s in starts])
        live = [b for b in range(B) if 0 <= tick - starts[b] < T]
        if not live:
            continue
        sub = {n: v[live] for n, v in state.items()}
        motion, sub = onnx_model.step_frames(feats[live, t[live]], t[live], style[live], sub)
        for n in state:
            state[n][live] = sub[n]
        for i, b in enumerate(live):
            np.testing.assert_allclose(motion[i], want[b][t[b]], atol=1e-6)


def test_export_refuses_models_it_cannot_export(tmp_path):
    with pytest.raises(TalkmeshError, match="causal VQ decoder and the Whisper"):
        export_onnx(build_tiny_codetalker(causal=False), tmp_path / "x.onnx")
    assert list(tmp_path.iterdir()) == []


def test_onnx_files_of_another_model_or_opset_are_one_line(tmp_path, exported):
    _, path = exported
    plain = tmp_path / "plain.onnx"
    torch.onnx.export(torch.nn.Linear(2, 2), (torch.zeros(1, 2),), str(plain), dynamo=False)
    with pytest.raises(TalkmeshError, match="not an ONNX file of talkmesh export-onnx"):
        load_model(plain)
    newer = tmp_path / "newer.onnx"
    proto = onnx.load(str(plain))
    proto.opset_import[0].version = 99
    onnx.save(proto, str(newer))
    with pytest.raises(TalkmeshError, match="ONNX Runtime cannot load it"):
        load_model(newer)
    corrupt = tmp_path / "corrupt.onnx"
    corrupt.write_bytes(b"\x08\x07garbage" * 10)
    with pytest.raises(TalkmeshError, match="ONNX Runtime cannot load it"):
        load_model(corrupt)
    other = tmp_path / "other.onnx"
    proto = onnx.load(str(path))
    for prop in proto.metadata_props:
        if prop.key == "talkmesh_format":
            prop.value = "7"
    onnx.save(proto, str(other))
    with pytest.raises(TalkmeshError, match="talkmesh ONNX format 7, this talkmesh reads 1"):
        load_model(other)
    with pytest.raises(TalkmeshError, match="no such ONNX file"):
        load_model(tmp_path / "missing.onnx")


def test_cli_export_refuses_existing_outputs_and_other_suffixes(tmp_path, exported, capsys):
    _, path = exported
    cases = [
        (["export-onnx", "codetalker-synth", "-o", str(path)], "already exists"),
        (["export-onnx", "codetalker-synth", "-o", str(tmp_path / "m.bin")], "ending in .onnx"),
        (["animate", str(CLIP), "--runtime", "onnxruntime", "--model", "procedural"], "not one"),
        (["animate", str(CLIP), "--runtime", "torch", "--model", str(path)], "runs releases"),
    ]
    for args, fragment in cases:
        assert main(args) != 0
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("talkmesh: error:") and fragment in err[0]
    assert list(tmp_path.iterdir()) == []


@pytest.mark.slow
def test_bundled_model_exports_and_animates_as_pytorch_does(tmp_path):
    """The CLI end to end: export-onnx, then animate with ONNX Runtime and with PyTorch."""
    run = [sys.executable, "-m", "talkmesh"]
    out = tmp_path / "ct.onnx"
    res = subprocess.run([*run, "export-onnx", "codetalker-synth", "-o", str(out)], text=True)
    assert res.returncode == 0 and out.is_file() and speech_path(out).is_file()
    common = [str(CLIP), "--head-motion", "0", "-q"]
    torch_run = ["--runtime", "torch"]
    for name, extra in (("torch", torch_run), ("onnx", ["--model", str(out)])):
        args = [*run, "animate", *common, *extra, "-o", str(tmp_path / f"{name}.npy")]
        assert subprocess.run(args).returncode == 0
    # .npy: float32 vertex positions (.npz keeps float16 offsets, whose rounding is 4 um)
    want, got = (np.load(tmp_path / f"{n}.npy") for n in ("torch", "onnx"))
    scale = np.abs(want - want.mean(0)).max()  # the motion's scale: offsets from its mean frame
    assert scale > 1e-3 and np.abs(got - want).max() <= TOLERANCE * scale
