"""Make the official-format fixtures that tests/test_official.py imports and compares against.

    python scripts/make_official_fixtures.py --official /path/to/FaceFormer [--official ...]

Each ``--official`` is a local checkout of one of the papers' code (FaceFormer: EvelynFan/FaceFormer);
this script imports it at run time (none of its code is copied here) and, per dataset setup:

1. builds the official model at a tiny size with random weights (seeded): the speech encoder is
   ``Wav2Vec2Config`` made tiny instead of ``from_pretrained``, everything else is the official
   class with the official dataset arguments (d_model, period, train subjects);
2. saves it exactly as the official trainer does (FaceFormer: ``torch.save(model.state_dict())``),
   with the weight-norm tensors under the torch 1.x names the released files carry
   (``weight_g``/``weight_v``);
3. runs the official prediction (``model.predict``) on ``speech.wav`` prepared as the official demo
   prepares it (16 kHz, the wav2vec2 processor's zero-mean unit-variance normalisation);
4. writes ``<family>_<dataset>.pth`` (the checkpoint) and ``<family>_<dataset>.npz`` (template,
   conditioning subject, the official output) to tests/fixtures/official/.

Only what cannot run here is patched: ``from_pretrained`` (no network) and, for transformers >= 4.x
where ``Wav2Vec2FeatureProjection`` returns ``(hidden, normed)`` instead of ``hidden``, that call
takes the first element (the same computation). The checkout's files are not modified.

MeshTalk (facebookresearch/meshtalk; its code needs torch and torchaudio, run this script with an
environment that has both) is saved as its ``Net.save`` does (``torch.save(state_dict())`` to
``encoder.pkl``, ``context_model.pkl``, ``vertex_unet.pkl``) under tests/fixtures/official/meshtalk/,
with the demo's smoothing masks as ``forehead_mask.txt`` / ``neck_mask.txt`` (its assets' format);
``meshtalk.npz`` holds the official outputs of ``animate_face.py``'s steps (``load_audio``,
``audio_chunking``, the audio encoder, ``ContextModel.sample`` with argmax and with Gumbel draws
under ``torch.manual_seed``, ``VertexUnet``, ``smooth_geom``). Its layers have hard-coded widths
(128-channel convolutions, 64 per head in the prior), so to stay small every weight is a window of
one of a few shared random vectors (``torch.save`` stores a shared storage once). Patched: the
module ``pytorch3d`` (imported for .obj reading, not used here) is a stub, and ``torchaudio.load``
(which needs torchcodec) reads the 16 kHz wav with soundfile.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "tests" / "fixtures" / "official"
NUM_VERTICES = 24  # tiny meshes: the architecture does not depend on the vertex count
SEED = 0
ROW_STEP = 7  # MeshTalk fixture: elements between the starts of a weight's rows
SAMPLE_SEED = 3  # torch.manual_seed before MeshTalk's Gumbel draws

VOCASET_SUBJECTS = (
    "FaceTalk_170728_03272_TA FaceTalk_170904_00128_TA FaceTalk_170725_00137_TA "
    "FaceTalk_170915_00223_TA FaceTalk_170811_03274_TA FaceTalk_170913_03279_TA "
    "FaceTalk_170904_03276_TA FaceTalk_170912_03278_TA"
)
BIWI_SUBJECTS = "F2 F3 F4 M3 M4 M5"


def tiny_wav2vec2_config():
    """wav2vec 2.0 with the official width (768: the official models hard-code Linear(768, d))
    but no transformer layer and 8-channel convolutions, so the fixture stays small. The CNN,
    feature projection, positional convolution and encoder norm all run."""
    from transformers import Wav2Vec2Config

    return Wav2Vec2Config(
        hidden_size=768,
        num_hidden_layers=0,
        num_attention_heads=4,
        intermediate_size=8,
        conv_dim=(8,) * 7,
        num_conv_pos_embeddings=4,
        num_conv_pos_embedding_groups=768,
        attn_implementation="eager",  # the official forward sets output_attentions
    )


def speech(path: Path) -> np.ndarray:
    """The committed wav as float32 at 16 kHz (it is stored at 16 kHz: no resampling)."""
    import soundfile as sf

    audio, sr = sf.read(str(path), dtype="float32")
    if sr != 16000 or audio.ndim != 1:
        raise SystemExit(f"{path}: expected 16 kHz mono")
    return audio


def processor_input(audio: np.ndarray) -> np.ndarray:
    """What the official demos feed the model: Wav2Vec2Processor's zero-mean unit-variance input."""
    from transformers import Wav2Vec2FeatureExtractor

    fe = Wav2Vec2FeatureExtractor(do_normalize=True, return_attention_mask=False)
    return np.squeeze(fe(audio, sampling_rate=16000).input_values)


def torch1_names(state: dict) -> dict:
    """Weight-norm tensors under the names torch 1.9 saved them with."""
    out = {}
    for k, v in state.items():
        k = k.replace("parametrizations.weight.original0", "weight_g")
        k = k.replace("parametrizations.weight.original1", "weight_v")
        out[k] = v.detach().clone()
    return out


def patch_encoder(model) -> None:
    """transformers >= 4.x: the feature projection returns (hidden, normed); 4.6.1 returned hidden."""
    projection = model.feature_projection
    forward = projection.forward

    def first(*args, **kwargs):
        out = forward(*args, **kwargs)
        return out[0] if isinstance(out, tuple) else out

    projection.forward = first


def faceformer(checkout: Path, wav: Path) -> None:
    sys.path.insert(0, str(checkout))
    import faceformer as official  # the checkout's faceformer.py

    config = tiny_wav2vec2_config()
    official.Wav2Vec2Model.from_pretrained = classmethod(lambda cls, *a, **k: cls(config))
    audio = speech(wav)
    for dataset, subjects, d, period in (
        ("vocaset", VOCASET_SUBJECTS, 32, 30),  # d_model: official 64 (tiny here)
        ("BIWI", BIWI_SUBJECTS, 32, 25),  # official 128
    ):
        torch.manual_seed(SEED)
        args = SimpleNamespace(
            dataset=dataset,
            vertice_dim=NUM_VERTICES * 3,
            feature_dim=d,
            period=period,
            train_subjects=subjects,
            device="cpu",
        )
        model = official.Faceformer(args)
        # the official motion decoder starts at zero: give it weights so the output moves
        torch.nn.init.normal_(model.vertice_map_r.weight, std=0.05)
        torch.nn.init.normal_(model.vertice_map_r.bias, std=0.01)
        model.eval()
        patch_encoder(model.audio_encoder)
        names = subjects.split()
        condition = len(names) // 2
        one_hot = torch.zeros(1, len(names))
        one_hot[0, condition] = 1
        template = torch.randn(NUM_VERTICES, 3, generator=torch.Generator().manual_seed(1)) * 0.1
        inputs = torch.from_numpy(processor_input(audio))[None]
        with torch.no_grad():
            out = model.predict(inputs, template.reshape(1, -1), one_hot)
        name = f"faceformer_{dataset.lower()}"
        torch.save(torch1_names(model.state_dict()), OUT / f"{name}.pth")
        np.savez(
            OUT / f"{name}.npz",
            template=template.numpy(),
            condition=np.array(names[condition]),
            subjects=np.array(names),
            vertices=out[0].reshape(-1, NUM_VERTICES, 3).numpy(),
        )
        print(f"{name}: {out.shape[1]} frames from {len(audio)} samples")
    sys.path.remove(str(checkout))


def codetalker(checkout: Path, wav: Path) -> None:
    """Stage 1 (the VQ-VAE) is saved by the official ``save_checkpoint`` as the stage-1 trainer
    does, stage 2 as the stage-2 trainer does (``stage=2``: every ``autoencoder.*`` tensor
    dropped), and stage 2 is built from the stage-1 file as the official demo builds it."""
    sys.path.insert(0, str(checkout))
    from base.baseTrainer import save_checkpoint
    from models.lib import wav2vec
    from models.stage2 import CodeTalker

    config = tiny_wav2vec2_config()
    wav2vec.Wav2Vec2Model.from_pretrained = classmethod(lambda cls, *a, **k: cls(config))
    audio = speech(wav)
    # tiny sizes, 8 stage-1 heads as released (shapes do not tell the head count; official:
    # hidden 1024, 6 layers, FF 1536, N 256; VOCASET H 16 x C 64,
    # BIWI H 8 x C 128 with maps between hidden and H x C; stage 2 d 1024, 6 / 12 layers)
    for dataset, subjects, H, C, hidden, period in (
        ("vocaset", VOCASET_SUBJECTS, 2, 8, 16, 30),  # VOCASET: hidden = H x C
        ("BIWI", BIWI_SUBJECTS, 2, 12, 16, 25),
    ):
        torch.manual_seed(SEED)
        args = SimpleNamespace(
            dataset=dataset,
            train_subjects=subjects,
            in_dim=NUM_VERTICES * 3,
            hidden_size=hidden,
            num_hidden_layers=1,
            num_attention_heads=8,
            intermediate_size=24,
            window_size=1,
            quant_factor=0,
            face_quan_num=H,
            neg=0.2,
            INaffine=False,
            n_embed=16,
            zquant_dim=C,
            autoencoder=f"stage1_{dataset}",
            feature_dim=32,
            vertice_dim=NUM_VERTICES * 3,
            device="cpu",
            period=period,
            n_head=4,
            num_layers=2,
            wav2vec2model_path="(tiny)",
            motion_weight=1.0,
            reg_weight=1.0,
        )
        stage1_module = __import__(f"models.stage1_{dataset}", fromlist=["VQAutoEncoder"])
        vq = stage1_module.VQAutoEncoder(args)
        # a trained codebook is spread like the encoder's outputs, not the tiny uniform init
        torch.nn.init.normal_(vq.quantize.embedding.weight, std=0.5)
        name = f"codetalker_{dataset.lower()}"
        save_checkpoint(vq, {"epoch": 200}, sav_path=str(OUT), filename=f"{name}_stage1.pth.tar")
        args.vqvae_pretrained_path = str(OUT / f"{name}_stage1.pth.tar")
        model = CodeTalker(args)
        torch.nn.init.normal_(model.feat_map.weight, std=0.5)  # zero-initialised officially
        model.eval()
        patch_encoder(model.audio_encoder)
        save_checkpoint(
            model, {"epoch": 100}, sav_path=str(OUT), filename=f"{name}_stage2.pth.tar", stage=2
        )
        names = subjects.split()
        condition = len(names) // 2
        one_hot = torch.zeros(1, len(names))
        one_hot[0, condition] = 1
        template = torch.randn(NUM_VERTICES, 3, generator=torch.Generator().manual_seed(1)) * 0.1
        inputs = torch.from_numpy(processor_input(audio))[None]
        with torch.no_grad():
            out = model.predict(inputs, template.reshape(1, -1), one_hot)
        np.savez(
            OUT / f"{name}.npz",
            template=template.numpy(),
            condition=np.array(names[condition]),
            subjects=np.array(names),
            vertices=out[0].reshape(-1, NUM_VERTICES, 3).numpy(),
        )
        print(f"{name}: {out.shape[1]} frames from {len(audio)} samples")
    sys.path.remove(str(checkout))


def shared_weights(modules: list[torch.nn.Module], seed: int) -> None:
    """Replace every parameter by a window of one of a few shared random vectors (chosen by its
    fan-in's scale; biases 0.02): rows start ROW_STEP elements apart, so a saved file holds a few
    small storages whatever the layer widths."""
    gen = torch.Generator().manual_seed(seed)
    params = [p for m in modules for p in m.parameters()]
    scales = (0.04, 0.12, 0.35)

    def group(p: torch.Tensor) -> float:
        if p.ndim == 1:
            return 0.02
        return min(scales, key=lambda s: abs(np.log(s * np.sqrt(p[0].numel()))))

    def layout(p: torch.Tensor) -> tuple[list[int], int]:
        strides = list(torch.empty(p.shape).stride())
        if p.ndim > 1:
            strides[0] = ROW_STEP
        return strides, sum((n - 1) * st for n, st in zip(p.shape, strides)) + 1

    sizes: dict[float, int] = {}
    for p in params:
        sizes[group(p)] = max(sizes.get(group(p), 0), layout(p)[1])
    pools = {s: (torch.rand(n + 97, generator=gen) * 2 - 1) * s * 3**0.5 for s, n in sizes.items()}
    for i, p in enumerate(params):
        strides, _ = layout(p)
        p.data = pools[group(p)].as_strided(p.shape, strides, (i * 13) % 97)


def obj_vertices(path: Path) -> torch.Tensor:
    """The ``v`` lines of an .obj file -> (V, 3) (the official demo reads it with pytorch3d)."""
    rows = [line.split()[1:4] for line in path.read_text().splitlines() if line.startswith("v ")]
    return torch.tensor(np.array(rows, dtype=np.float32))


def meshtalk_models(checkout: Path, size: str):
    """The official networks: ``tiny`` (6172 -> 24 vertices, 16 -> 2 heads, 128 -> 12 classes,
    128 -> 16 latent widths, the layers' own widths official, weights from shared random vectors)
    or ``released`` (animate_face.py's sizes, the official initialisation, the checkout's vertex
    statistics, template and smoothing masks) or ``paper`` (the same with the paper's 64 heads)."""
    from models.context_model import ContextModel
    from models.encoders import MultimodalEncoder
    from models.vertex_unet import VertexUnet

    gen = torch.Generator().manual_seed(SEED)
    torch.manual_seed(SEED)
    if size in ("released", "paper"):
        V, H, C, D = 6172, 16 if size == "released" else 64, 128, 128
        assets = checkout / "assets"
        mean = torch.from_numpy(np.load(assets / "face_mean.npy")).float()
        stddev = torch.from_numpy(np.load(assets / "face_std.npy")).float()
        template = obj_vertices(assets / "face_template.obj")
        masks = torch.from_numpy(
            np.stack([np.loadtxt(assets / f"{n}_mask.txt") for n in ("forehead", "neck")])
        ).float()
    else:
        V, H, C, D = NUM_VERTICES, 2, 12, 16
        mean = torch.randn(V, 3, generator=gen) * 0.1
        stddev = torch.rand(V, 3, generator=gen) * 0.01 + 0.005
        template = mean + torch.randn(V, 3, generator=gen) * 0.01
        masks = torch.rand(2, V, generator=gen)
    geom_unet = VertexUnet(classes=C, heads=H, n_vertices=V, mean=mean, stddev=stddev).eval()
    context_model = ContextModel(classes=C, heads=H, audio_dim=D).eval()
    encoder = MultimodalEncoder(
        classes=C, heads=H, expression_dim=D, audio_dim=D, n_vertices=V, mean=mean, stddev=stddev
    ).eval()
    if size == "tiny":
        shared_weights([geom_unet, context_model, encoder], SEED)
    return encoder, context_model, geom_unet, template.reshape(V, 3), masks


def meshtalk(checkout: Path, wav: Path, size: str = "tiny", out: Path | None = None) -> None:
    """Save the official MeshTalk (``meshtalk_models``) as Net.save does and run
    animate_face.py's steps on ``wav``: argmax codes, then Gumbel draws after
    ``torch.manual_seed(SAMPLE_SEED)``; ``official_seconds`` times each generation."""
    import time
    import types

    import torchaudio as ta

    stub = types.ModuleType("pytorch3d")
    stub.io = types.ModuleType("pytorch3d.io")
    stub.io.load_obj = None
    sys.modules.setdefault("pytorch3d", stub)
    sys.modules.setdefault("pytorch3d.io", stub.io)
    ta.load = lambda path: (torch.from_numpy(speech(Path(path)))[None], 16000)
    sys.path.insert(0, str(checkout))
    from utils.helpers import audio_chunking, load_audio, smooth_geom

    encoder, context_model, geom_unet, template, masks = meshtalk_models(checkout, size)
    V = template.shape[0]
    out = out or OUT / "meshtalk"
    out.mkdir(parents=True, exist_ok=True)
    for net in (encoder, context_model, geom_unet):  # as Net.save writes them
        torch.save(net.state_dict(), out / f"{net.model_name}.pkl")
    for name, mask in zip(("forehead_mask", "neck_mask"), masks):
        np.savetxt(out / f"{name}.txt", mask.numpy())
    result = {"template": template.numpy(), "masks": masks.numpy()}
    with torch.no_grad():
        for mode, argmax in (("argmax", True), ("gumbel", False)):
            start = time.perf_counter()  # animate_face.py from the audio file on
            audio = audio_chunking(load_audio(str(wav)), frame_rate=30, chunk_size=16000)
            audio_code = encoder.audio_encoder(audio.unsqueeze(0))["code"]
            torch.manual_seed(SAMPLE_SEED)
            one_hot = context_model.sample(audio_code, argmax=argmax)["one_hot"]
            T = one_hot.shape[1]
            geom = template.view(1, 1, V, 3).expand(-1, T, -1, -1).contiguous()
            geom = geom_unet(geom, one_hot)["geom"].squeeze(0)
            smoothed = smooth_geom(smooth_geom(geom, masks[0]), masks[1])
            result[f"{mode}_seconds"] = np.array(time.perf_counter() - start)
            result[f"{mode}_codes"] = one_hot[0].argmax(-1).numpy()
            result[f"{mode}_vertices"] = geom.numpy()
            result[f"{mode}_smoothed"] = smoothed.numpy()
        # teacher forcing on the drawn codes and the encoder on the generated motion
        result["prior_logprobs"] = context_model(one_hot, audio_code)["logprobs"][0].numpy()
        result["encoder_logprobs"] = encoder(geom[None], audio.unsqueeze(0))["logprobs"][0].numpy()
        result["audio_code"] = audio_code[0].numpy()
    result["sample_seed"] = np.array(SAMPLE_SEED)
    np.savez(out / "meshtalk.npz", **result)
    print(f"meshtalk ({size}): {T} frames from {load_audio(str(wav)).shape[1]} samples -> {out}")
    sys.path.remove(str(checkout))


def detect(checkout: Path) -> str:
    if (checkout / "models" / "context_model.py").is_file():
        return "meshtalk"
    if (checkout / "faceformer.py").is_file():
        return "faceformer"
    if (checkout / "models" / "stage2.py").is_file():
        return "codetalker"
    raise SystemExit(f"{checkout}: not a checkout of FaceFormer, CodeTalker or MeshTalk")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument(
        "--official",
        type=Path,
        action="append",
        required=True,
        help="a local checkout of the official code (repeatable)",
    )
    p.add_argument("--wav", type=Path, default=OUT / "speech.wav")
    p.add_argument(
        "--meshtalk-size",
        choices=("tiny", "released", "paper"),
        default="tiny",
        help="MeshTalk: the tiny fixture, or the released or paper sizes (random weights; for "
        "bench/official_equivalence.py --meshtalk DIR: use with --out)",
    )
    p.add_argument("--out", type=Path, help="MeshTalk: write here instead of the fixtures")
    args = p.parse_args()
    OUT.mkdir(parents=True, exist_ok=True)
    for checkout in args.official:
        kind = detect(checkout)
        if kind == "meshtalk":
            meshtalk(checkout.resolve(), args.wav, args.meshtalk_size, args.out)
        else:
            {"faceformer": faceformer, "codetalker": codetalker}[kind](checkout.resolve(), args.wav)


if __name__ == "__main__":
    main()
