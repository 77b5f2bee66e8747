"""`talkmesh serve --runtime onnxruntime`: an .onnx export's POST /animate jobs run the exported
graphs and equal the PyTorch runtime; its streams are refused in one line (the exported speech
encoder reads whole windows of audio); a runtime that disagrees with a --model is one line."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from starlette.testclient import TestClient
from test_onnx import tiny_model

from talkmesh.cli import main
from talkmesh.models.onnx import export_onnx
from talkmesh.serve.server import create_app

CLIP = Path(
    "/usr/share/pocketsphinx/test/data/librivox/sense_and_sensibility_01_austen_64kb-0880.wav"
)  # 3.0 s of speech
TOLERANCE = 1e-4  # of the motion's scale (its largest offset)


@pytest.fixture(scope="module")
def tiny_onnx(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("onnx") / "tiny.onnx"
    export_onnx(tiny_model(), path)
    return path


def test_a_session_asking_for_an_onnx_model_is_refused_in_one_line(tiny_onnx):
    from starlette.websockets import WebSocketDisconnect

    with TestClient(create_app(["procedural", str(tiny_onnx)])) as client:
        assert client.get("/health").json()["models"] == ["procedural", "tiny"]
        with client.websocket_connect("/ws/stream?model=tiny") as ws:
            reply = ws.receive_json()
            with pytest.raises(WebSocketDisconnect) as closed:
                ws.receive_json()
    assert reply["type"] == "error" and closed.value.code == 1008, (reply, closed.value.code)
    message = reply["message"]
    assert "\n" not in message and "cannot stream" in message, message
    assert "POST /animate?model=tiny" in message, message


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
