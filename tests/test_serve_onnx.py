"""`talkmesh serve --runtime onnxruntime`: an .onnx export's POST /animate jobs run the exported
graphs and equal the PyTorch runtime; its sessions stream what the PyTorch model streams, without
torch (talkmesh.models.onnx_stream); a runtime that disagrees with a --model is one line."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from starlette.testclient import TestClient
from test_onnx import tiny_model

from talkmesh.cli import main
from talkmesh.face.assets import load_head
from talkmesh.models.onnx import export_onnx
from talkmesh.serve.server import create_app

CLIP = Path(
    "/usr/share/pocketsphinx/test/data/librivox/sense_and_sensibility_01_austen_64kb-0880.wav"
)  # 3.0 s of speech
TOLERANCE = 1e-4  # of the motion's scale (its largest offset)


@pytest.fixture(scope="module")
def head_onnx(tmp_path_factory):
    """A tiny CodeTalker of the served head's vertices (Whisper encoder, causal VQ decoder):
    its release (ct_torch.safetensors) and its export (ct_onnx.onnx)."""
    from talkmesh.models.release import save_model

    model = tiny_model(num_vertices=load_head().num_vertices)
    folder = tmp_path_factory.mktemp("onnx")
    save_model(model, folder / "ct_torch.safetensors")
    export_onnx(model, folder / "ct_onnx.onnx")
    return folder / "ct_torch.safetensors", folder / "ct_onnx.onnx"


def _session(client, name: str, pcm: np.ndarray, offsets: int = 1) -> tuple[dict, list]:
    """The hello and the frames of a session that streams ``pcm`` (int16) in 100 ms messages."""
    from talkmesh.serve.protocol import decode_frame

    with client.websocket_connect(f"/ws/stream?model={name}&offsets={offsets}&idle=0") as ws:
        hello = ws.receive_json()
        for i in range(0, len(pcm), 1600):
            ws.send_bytes(pcm[i : i + 1600].tobytes())
        ws.send_json({"type": "end"})
        frames = []
        while (message := ws.receive())["type"] != "websocket.close":
            if message.get("bytes") is not None:
                frames.append(decode_frame(message["bytes"]))
    return hello, frames


def test_a_session_streams_an_onnx_model_as_pytorch_streams_it(head_onnx):
    """Sessions of the release and of its export in one server: the same look-ahead (300 ms and
    the rest of a 3-frame block), every frame, and the same frames (the ONNX session without
    torch's kernels): ARKit weights within 1e-3, offsets within float16's rounding; sessions
    without offsets (the projections onto the blendshapes alone) the same weights."""
    from talkmesh.audio.loading import SAMPLE_RATE, load_audio

    wave = load_audio(CLIP)
    pcm = (np.clip(wave, -1, 1) * 32767).astype("<i2")
    with TestClient(create_app([str(p) for p in head_onnx])) as client:
        assert client.get("/health").json()["models"] == ["ct_torch", "ct_onnx"]
        hello, want = _session(client, "ct_torch", pcm)
        onnx_hello, got = _session(client, "ct_onnx", pcm)
        # without offsets the model gives the frames' projections onto the blendshapes alone
        weights_only = [_session(client, name, pcm, 0)[1] for name in ("ct_torch", "ct_onnx")]
    assert onnx_hello["lookahead_ms"] == hello["lookahead_ms"] == pytest.approx(300 + 2000 / 30)
    assert [f.index for f in got] == list(range(round(len(wave) / SAMPLE_RATE * 30)))
    assert len(want) == len(got)
    w_got, w_want = (np.stack([f.weights for f in x]) for x in (got, want))
    assert np.ptp(w_want, axis=0).max() > 0.1  # the weights move
    assert np.abs(w_got - w_want).max() <= 1e-3
    w_torch, w_onnx = (np.stack([f.weights for f in x]) for x in weights_only)
    assert np.abs(w_onnx - w_torch).max() <= 1e-3 and np.abs(w_torch - w_want).max() <= 1e-3
    o_got, o_want = (np.stack([f.offsets for f in x]).astype(np.float32) for x in (got, want))
    assert np.abs(o_got - o_want).max() <= 2e-3 * np.abs(o_want).max()  # float16: 2^-10


def test_an_onnx_stream_never_imports_torch(head_onnx):
    """open_stream on an .onnx file in a fresh process: frames for the audio, no torch."""
    path = head_onnx[1]
    code = (
        "import sys\nimport numpy as np\n"
        "from talkmesh.audio.loading import load_audio\n"
        "from talkmesh.serve.stream import open_stream\n"
        f"s = open_stream({str(path)!r})\n"
        f"wave = load_audio({str(CLIP)!r})\n"
        "frames = [f for i in range(0, len(wave), 320) for f in s.push(wave[i:i + 320])]\n"
        "frames += s.flush()\n"
        "print(len(frames), 'torch' in sys.modules)\n"
    )
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert res.stdout.split() == ["90", "False"], res.stderr[-2000:]


def test_an_onnx_file_of_another_kind_stops_the_server_in_one_line(tmp_path, capsys):
    import onnx
    from onnx import TensorProto, helper

    graph = helper.make_graph(
        [helper.make_node("Identity", ["x"], ["y"])],
        "other",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1])],
    )
    other = tmp_path / "other.onnx"
    onnx.save(helper.make_model(graph), str(other))
    args = ["serve", "--runtime", "onnxruntime", "--model", str(other), "--port", "0", "-q"]
    assert main(args) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "not an ONNX file of talkmesh export-onnx" in err, err


@pytest.mark.parametrize(
    "args, says",
    [
        (["--runtime", "onnxruntime"], "procedural is not one"),
        (["--runtime", "onnxruntime", "--model", "codetalker-synth"], "export codetalker-synth"),
        (["--runtime", "torch", "--model", "x.onnx"], "pass --runtime onnxruntime"),
    ],
)
def test_a_runtime_that_disagrees_with_the_model_is_one_line(args, says, capsys):
    assert main(["serve", *args, "--port", "0", "-q"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("talkmesh: error: --runtime"), err
    assert says in err, err


@pytest.mark.slow
def test_animate_jobs_on_onnx_runtime_equal_the_torch_runtime(tmp_path):
    """The bundled model exported: POST /animate?model=ct answers the glb of the exported graphs,
    and the job's animation (:func:`talkmesh.pipeline.animate`, what the job runs) equals the
    PyTorch release's within 1e-4 of the motion's scale; its ARKit weights in the glb equal those
    of the PyTorch animation written the same way."""
    import torch

    from talkmesh.audio.loading import load_audio
    from talkmesh.models.release import load_model
    from talkmesh.output import write_animation
    from talkmesh.output.avatar import read_glb
    from talkmesh.output.gltf import _read_accessor
    from talkmesh.pipeline import animate

    path = tmp_path / "ct.onnx"
    with torch.no_grad():
        export_onnx(load_model("codetalker-synth"), path)
    with TestClient(create_app([str(path)])) as client:
        response = client.post("/animate?format=glb&model=ct", content=CLIP.read_bytes())
    assert response.status_code == 200, response.text
    served = tmp_path / "served.glb"
    served.write_bytes(response.content)

    audio = load_audio(CLIP)
    want = animate(audio, model="codetalker-synth")
    got = animate(audio, model=str(path))
    scale = np.abs(want.vertices - want.vertices[:1].mean(0)).max()
    assert scale > 1e-3
    difference = np.abs(got.vertices - want.vertices).max() / scale
    assert difference <= TOLERANCE, difference

    torch_glb = tmp_path / "torch.glb"
    write_animation(want, torch_glb, overwrite=True)

    def weights(glb: Path) -> np.ndarray:
        gltf, binary = read_glb(glb)
        sampler = next(
            a["samplers"][c["sampler"]]
            for a in gltf["animations"]
            for c in a["channels"]
            if c["target"]["path"] == "weights"
        )
        return np.asarray(_read_accessor(gltf, binary, sampler["output"]))

    served_w, torch_w = weights(served), weights(torch_glb)
    assert served_w.shape == torch_w.shape
    assert np.abs(served_w - torch_w).max() <= 1e-3, np.abs(served_w - torch_w).max()
    print(f"\nserve --runtime onnxruntime: motion {difference:.1e} of its scale from torch")
