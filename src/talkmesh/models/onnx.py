"""Learned models as ONNX files, and generation with ONNX Runtime.

``talkmesh export-onnx MODEL -o model.onnx`` writes two graphs (:meth:`MotionModel.onnx_graphs`;
the bundled CodeTalker's are in :mod:`talkmesh.models.codetalker.export`):

* ``model.speech.onnx``: the speech encoder, ``mel`` (1, 80, 2N) float32, one window of at most
  30 s of Whisper's log-mel (:func:`talkmesh.models.whisper.log_mel`) -> ``features`` (1, N, D)
  at 50 Hz;
* ``model.onnx``: one frame of generation, the frame's speech feature and the state in, its motion
  and the next state out (every input and output has the batch axis ``B`` first, so B streams
  step together). The autoregressive loop does not export: the caller runs it, one call per
  frame (:class:`OnnxModel` does).

``model.onnx`` carries in its metadata what a runtime needs: ``talkmesh_format``, the family,
``fps``, ``num_vertices``, the speech graph's file name, the style names and their vectors (the
mean is a speaker the model has not heard), the state's names and shapes, and for a model with a
head term (``stage2.head_pairs``) its lip pairs and maps (``head``). A model whose VQ decoder
hears the head too (``stage2.head_decoder``) has one more step input, ``face`` (B, hidden), that
the runtime computes from the template once per stream (:meth:`OnnxModel.face`). Opset 17.

:class:`OnnxModel` has the surface :func:`talkmesh.pipeline.animate` uses of a model, so a
``.onnx`` file is a ``--model`` like a release (:func:`talkmesh.models.release.load_model`
dispatches on the suffix). It runs without torch: the log-mel and the interpolation of the
features to the motion frames in numpy (:mod:`talkmesh.audio.logmel`, the numbers ``generate``
computes), the networks in ONNX Runtime, the speech graph on ONNX Runtime's threads and the step
graph on :func:`~talkmesh.models.threads.step_thread_count`'s (one: a frame's small products
lose more to a team of threads than they gain).
"""

from __future__ import annotations

import json
import os
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from talkmesh.audio.logmel import HOP_LENGTH, interpolate_rows, log_mel
from talkmesh.audio.resamplers import POLYPHASE
from talkmesh.constants import CHUNK_FRAMES, frames_for_audio
from talkmesh.errors import MissingDependencyError, TalkmeshError
from talkmesh.models.threads import step_thread_count

if TYPE_CHECKING:
    from torch import Tensor, nn

FORMAT = "1"
OPSET = 17
MAX_WINDOW = 1500  # encoder frames per window (30 s at 50 Hz): Whisper's positions
ENCODER_HOP = 2 * HOP_LENGTH  # one speech feature per 20 ms (50 Hz)


def speech_path(path: Path) -> Path:
    """The speech graph beside ``model.onnx``: ``model.speech.onnx``."""
    return path.with_name(path.stem + ".speech.onnx")


def _onnx():
    try:
        import onnx
    except ImportError:
        raise MissingDependencyError("onnx", "onnx", "talkmesh export-onnx") from None
    return onnx


def export_onnx(model: nn.Module, path: str | Path, opset: int = OPSET) -> list[Path]:
    """Write ``model``'s two graphs (module docstring) -> the files written (step, speech).
    Each is written under a temporary name and renamed into place."""
    import torch

    onnx = _onnx()
    path = Path(path)
    encoder, step = model.onnx_graphs()
    names = ["x_in", "conv", *step.ring_names()]
    shapes = step.state_shapes()
    K = len(model.styles)
    with torch.no_grad(), warnings.catch_warnings():
        # the styles alone: the runtime adds the head term of the template it drives
        table = model.style_vector(torch.arange(K)) - model.head_term(None)
        mean = model.style_vector(None, torch.full((1, K), 1.0 / K))
        dim = model.audio_map.in_features
        example = (torch.zeros(1, dim), torch.zeros(1, dtype=torch.long), mean)
        face = model.decoder_face(None)
        example += () if face is None else (face,)
        example += tuple(torch.zeros(1, *shapes[n]) for n in names)
        outputs = ["motion", *(f"next_{n}" for n in names)]
        inputs = [*step.input_names(), *names]
        tmp_step, tmp_speech = path.with_suffix(".tmp"), speech_path(path).with_suffix(".tmp")
        # the tracer's notes on shape checks and unpacking: the shapes it fixes are checked by
        # the equality tests (tests/test_onnx.py), at other lengths than the example's
        warnings.simplefilter("ignore", torch.jit.TracerWarning)
        warnings.simplefilter("ignore", DeprecationWarning)
        warnings.simplefilter("ignore", FutureWarning)
        try:
            torch.onnx.export(
                step, example, str(tmp_step), input_names=inputs, output_names=outputs,
                dynamic_axes={n: {0: "B"} for n in inputs + outputs}, opset_version=opset,
                dynamo=False,
            )  # fmt: skip
            mel = torch.zeros(1, encoder.encoder.config.num_mel_bins, 200)
            torch.onnx.export(
                encoder, (mel,), str(tmp_speech), input_names=["mel"], output_names=["features"],
                dynamic_axes={"mel": {2: "2N"}, "features": {1: "N"}}, opset_version=opset,
                dynamo=False,
            )  # fmt: skip
            proto = onnx.load(str(tmp_step))
            meta = {
                "talkmesh_format": FORMAT,
                "family": model.family,
                "fps": repr(float(model.motion_fps)),
                "num_vertices": str(model.num_vertices),
                "speech": speech_path(path).name,
                "speech_dim": str(dim),
                "n_mels": str(mel.shape[1]),
                "styles": json.dumps(list(model.styles)),
                "style_vectors": json.dumps(table.tolist()),
                "state": json.dumps({n: list(shapes[n]) for n in names}),
            }
            if model.head_map is not None:  # the head terms, computed by the runtime
                meta["head"] = json.dumps(_head_meta(model))
            for key, value in meta.items():
                proto.metadata_props.add(key=key, value=value)
            onnx.save(proto, str(tmp_step))
            os.replace(tmp_speech, speech_path(path))
            os.replace(tmp_step, path)
        finally:
            for tmp in (tmp_step, tmp_speech):
                tmp.unlink(missing_ok=True)
    return [path, speech_path(path)]


def _head_meta(model: nn.Module) -> dict:
    """The ``head`` metadata: the lip pairs, their standardisation and the style's map
    (``weight``, ``bias``), with the VQ decoder's (``decoder_weight``, ``decoder_bias``) where the
    model has one."""
    s2 = model.cfg.stage2
    head = {
        "pairs": list(s2.head_pairs),
        "mean": list(s2.head_mean),
        "std": list(s2.head_std),
        "scale": float(model.head_scale),
        "weight": model.head_map.weight.float().tolist(),
        "bias": model.head_map.bias.float().tolist(),
    }
    if model.decoder_head is not None:
        head["decoder_weight"] = model.decoder_head.weight.float().tolist()
        head["decoder_bias"] = model.decoder_head.bias.float().tolist()
    return head


class OnnxModel:
    """An exported model run by ONNX Runtime (CPU), with the surface of a
    :class:`~talkmesh.models.base.MotionModel` that animation uses (``generate``,
    ``generate_chunks``, ``styles``, ``motion_fps``, ``num_vertices``, ``default_frames``).

    Raises:
        TalkmeshError: the file is not a talkmesh export (another model), of another format, or
            ONNX Runtime cannot load it (a newer opset, a corrupt file).
    """

    family = "onnx"
    resampler = POLYPHASE  # an export of talkmesh's own models, which hear polyphase audio

    def __init__(self, path: str | Path, threads: int | None = None) -> None:
        try:
            import onnxruntime as ort
        except ImportError:
            raise MissingDependencyError("onnxruntime", "onnx", "ONNX models") from None
        self.path = Path(path)
        options, step_options = ort.SessionOptions(), ort.SessionOptions()
        if threads:
            options.intra_op_num_threads = threads
        for o in (options, step_options):  # idle threads sleep: they would spin on the cores
            o.add_session_config_entry("session.intra_op.allow_spinning", "0")
        step_options.intra_op_num_threads = threads or step_thread_count() or 0
        self.step = _session(ort, self.path, step_options)
        meta = self.step.get_modelmeta().custom_metadata_map
        if "talkmesh_format" not in meta:
            raise TalkmeshError(
                f"{self.path}: not an ONNX file of talkmesh export-onnx (no talkmesh metadata); "
                "export the model with `talkmesh export-onnx MODEL -o FILE.onnx`"
            )
        if meta["talkmesh_format"] != FORMAT:
            raise TalkmeshError(
                f"{self.path}: talkmesh ONNX format {meta['talkmesh_format']}, this talkmesh "
                f"reads {FORMAT}: export the model again"
            )
        self.speech = _session(ort, self.path.with_name(meta["speech"]), options)
        self.motion_fps = float(meta["fps"])
        self.num_vertices = int(meta["num_vertices"])
        self.styles = tuple(json.loads(meta["styles"]))
        self.style_vectors = np.array(json.loads(meta["style_vectors"]), np.float32)
        self.state = {n: tuple(s) for n, s in json.loads(meta["state"]).items()}
        self.n_mels = int(meta["n_mels"])
        self.head = json.loads(meta["head"]) if "head" in meta else None
        # the VQ decoder's head term: an input of the step graph
        self.has_face = self.head is not None and "decoder_weight" in self.head
        self.average_face = self.face()  # (1, hidden) or None: fed where a caller gives none

    def default_frames(self, samples: int) -> int:
        return frames_for_audio(samples, self.motion_fps)

    def int8_copy(self, layers: str) -> OnnxModel:
        raise TalkmeshError("--int8 applies to PyTorch models, not to an .onnx file")

    def features(self, audio: np.ndarray, num_frames: int) -> np.ndarray:
        """(S,) 16 kHz audio -> (num_frames, D) speech features, as ``generate`` computes them:
        the log-mel in windows of 30 s, each encoded on its own, interpolated to the frames."""
        n = len(audio)
        padded = np.zeros(-(-n // ENCODER_HOP) * ENCODER_HOP, np.float32)
        padded[:n] = audio
        mel = log_mel(padded, self.n_mels)[None]
        parts = [
            self.speech.run(None, {"mel": mel[..., i : i + 2 * MAX_WINDOW]})[0][0]
            for i in range(0, mel.shape[-1], 2 * MAX_WINDOW)
        ]
        return interpolate_rows(np.concatenate(parts)[: -(-n // ENCODER_HOP)], num_frames)

    def style(
        self, style_weights: np.ndarray | None, template: np.ndarray | None = None
    ) -> np.ndarray:
        """(K,) or (1, K) weights over the styles (None: all alike) -> (1, d) style vector,
        with the head term of ``template`` (V, 3) where the model has one (CodeTalker.head_term)."""
        K = len(self.styles)
        w = np.full(K, 1.0 / K) if style_weights is None else np.asarray(style_weights)
        style = w.reshape(1, K).astype(np.float32) @ self.style_vectors
        if self.head is not None:
            style = style + self._head_map("weight", "bias", template)
        return style.astype(np.float32)

    def face(self, template: np.ndarray | None = None) -> np.ndarray | None:
        """(1, hidden) the VQ decoder's head term of ``template`` (V, 3) (None: the training
        templates' average head), the step graph's ``face`` input (CodeTalker.decoder_face);
        None for a model without one."""
        if not self.has_face:
            return None
        return self._head_map("decoder_weight", "decoder_bias", template).astype(np.float32)

    def _head_map(self, weight: str, bias: str, template: np.ndarray | None) -> np.ndarray:
        """(1, out) the head map ``weight``/``bias`` of the metadata on the standardised lip
        distances of ``template`` (V, 3) (CodeTalker.head_input); its bias alone for None."""
        h = self.head
        out = np.asarray(h[bias], np.float32)[None]
        if template is not None:
            pairs = np.asarray(h["pairs"], np.int64).reshape(-1, 2)
            t = np.asarray(template, np.float32).reshape(-1, 3)
            dist = np.linalg.norm(t[pairs[:, 0]] - t[pairs[:, 1]], axis=-1)
            z = (dist - np.asarray(h["mean"])) / np.asarray(h["std"]) * h["scale"]
            out = out + (np.asarray(h[weight], np.float32) @ z.astype(np.float32))
        return out

    def open_frame_stream(
        self,
        style_weights: np.ndarray | None = None,
        lookahead_ms: float | None = None,
        template: np.ndarray | None = None,
    ):
        """One stream's frames (:class:`talkmesh.models.onnx_stream.OnnxFrameStream`): the
        speech graph on windows a block of frames at a time, ``lookahead_ms`` (None: 300 ms)
        after each block, the step graph on the streams of this model together."""
        from talkmesh.models.onnx_stream import OnnxFrameStream

        template = None if template is None else np.asarray(template, np.float32)
        return OnnxFrameStream(self, style_weights, lookahead_ms, template)

    def start(self, style: np.ndarray) -> dict[str, np.ndarray]:
        """The state of B streams before their first frame; ``style`` (B, d)."""
        state = {n: np.zeros((len(style), *s), np.float32) for n, s in self.state.items()}
        state["x_in"] = style[:, None].copy()
        return state

    def step_frames(
        self,
        feature: np.ndarray,
        t: np.ndarray,
        style: np.ndarray,
        state: dict[str, np.ndarray],
        face: np.ndarray | None = None,
    ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """One frame of B streams: feature (B, D), t (B,) int64 -> motion (B, V * 3), next state.
        ``face`` (B, hidden): their VQ decoder's head term (:meth:`face`), for a model with one
        (None: the average head's)."""
        feed = {"feature": feature, "t": t, "style": style, **state}
        if self.has_face:
            feed["face"] = np.repeat(self.average_face, len(feature), 0) if face is None else face
        out = self.step.run(None, feed)
        return out[0], dict(zip(self.state, out[1:]))

    def frames(
        self,
        wave: np.ndarray,
        template: np.ndarray,
        style_weights: np.ndarray | None = None,
        num_frames: int | None = None,
        chunk: int = CHUNK_FRAMES,
    ) -> Iterator[np.ndarray]:
        """(S,) 16 kHz audio, template (V, 3) -> vertices (t, V, 3) float32, ``chunk`` frames at
        a time: generation without torch."""
        wave = np.asarray(wave, np.float32)
        num_frames = num_frames or self.default_frames(len(wave))
        feats = self.features(wave, num_frames)
        style = self.style(style_weights, template)
        face = self.face(template)
        state = self.start(style)
        base = np.asarray(template, np.float32).reshape(1, -1)
        out = []
        for t in range(num_frames):
            motion, state = self.step_frames(feats[t : t + 1], np.array([t]), style, state, face)
            out.append(motion[0] + base[0])
            if len(out) == chunk or t == num_frames - 1:
                yield np.stack(out).reshape(len(out), -1, 3)
                out = []

    def generate_chunks(
        self,
        audio,
        template: Tensor,
        *,
        style_weights: Tensor | None = None,
        num_frames: int | None = None,
        seed: int = 0,
        mode: str = "fast",
        chunk: int = CHUNK_FRAMES,
    ) -> Iterator[Tensor]:
        """Vertices (1, t, V, 3) ``chunk`` frames at a time, as a model's ``generate_chunks``
        (torch tensors in and out; :meth:`frames` is the same without torch)."""
        import torch

        wave = np.asarray(audio[0] if isinstance(audio, torch.Tensor) else audio, np.float32)
        weights = None if style_weights is None else style_weights.numpy()
        for verts in self.frames(wave, template.numpy()[0], weights, num_frames, chunk):
            yield torch.from_numpy(verts)[None]

    def generate(
        self, audio: Tensor, template: Tensor, *, style_weights: Tensor | None = None, **options
    ) -> Tensor:
        """audio (1, S), template (1, V, 3) -> vertices (1, T, V, 3)."""
        import torch

        chunks = self.generate_chunks(audio, template, style_weights=style_weights, **options)
        return torch.cat(list(chunks), dim=1)


def _session(ort, path: Path, options):
    if not path.is_file():
        raise TalkmeshError(f"{path}: no such ONNX file (export-onnx writes it beside model.onnx)")
    try:
        return ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
    except Exception as e:  # onnxruntime raises its own classes for corrupt files and opsets
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise TalkmeshError(f"{path}: ONNX Runtime cannot load it ({first[:200]})") from None
