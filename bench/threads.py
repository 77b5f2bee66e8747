"""PyTorch threads for step-by-step generation: each family with PyTorch's default threads and
with talkmesh's thread policy (:mod:`talkmesh.models.threads`), on the machine as it is and with
a competing load on every core.

    python bench/threads.py [--seconds 2] [--families codetalker faceformer meshtalk synth]

Models, random weights (seeded) at the papers' sizes, as imported releases are built:

* ``codetalker``: CodeTalker VOCASET (stage 1: 1024 wide, 6 layers, 16 x 64 codes of 256; stage
  2: 1024 wide, 6 layers; wav2vec 2.0 base), ``exact`` mode (the imported releases' mode);
* ``faceformer``: FaceFormer VOCASET (d_model 64, one layer; wav2vec 2.0 base), ``fast`` mode;
* ``meshtalk``: the released MeshTalk (6172 vertices, 16 heads x 128 classes), the prior's
  sampler with Gumbel draws and the decoder;
* ``synth``: the bundled ``codetalker-synth`` (Whisper tiny encoder), ``fast`` mode through
  ``generate_chunks`` (what ``talkmesh animate`` runs; its speech windows run inside the loop).

Each row is one ``generate`` call on the same speech (the fixtures' clip repeated to
``--seconds``), after an untimed warm-up, timed with ``default`` threads (PyTorch's own count
throughout: ``TALKMESH_STEP_THREADS=0``) and ``policy`` (the step loops on ``STEP_THREADS``).
``busy`` rows run while one spinning process per core competes for the CPUs (started before and
stopped after each pair). The speed-ups are ratios within one run, which is what to compare on a
machine shared with other jobs.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import torch

from talkmesh.audio.loading import load_audio
from talkmesh.models.threads import ENV, STEP_THREADS, usable_cpus

ROOT = Path(__file__).resolve().parents[1]
SPEECH = ROOT / "tests" / "fixtures" / "official" / "speech.wav"
FAMILIES = ("codetalker", "faceformer", "meshtalk", "synth")


def wav2vec2_base() -> dict:
    from transformers import Wav2Vec2Config

    return Wav2Vec2Config().to_dict()


def codetalker_paper():
    from talkmesh.models.codetalker.model import CodeTalker, CodeTalkerConfig, Stage2Config
    from talkmesh.models.codetalker.vq import VQConfig
    from talkmesh.models.official import SUBJECTS
    from talkmesh.models.speech import SpeechEncoderConfig

    vq = VQConfig(
        num_vertices=5023,
        hidden=1024,
        layers=6,
        heads=8,
        ff=1536,
        components=16,
        code_dim=64,
        codebook_size=256,
        instance_norm=True,
        gelu_tanh=True,
        final_norm=False,
        frame_positions=False,
    )
    speech = SpeechEncoderConfig(
        kind="wav2vec2", frame_rate=30.0, resample="cnn", normalize=True, hf_config=wav2vec2_base()
    )
    stage2 = Stage2Config(
        d_model=1024,
        heads=4,
        layers=6,
        period=30,
        ff=2048,
        styles=SUBJECTS["vocaset"],
        attention_window=600,
        postnorm=True,
        interleaved_ppe=True,
        speech=speech,
    )
    net = CodeTalker(CodeTalkerConfig(vq=vq, stage2=stage2, motion_fps=30.0))
    return net, "exact"


def faceformer_paper():
    from talkmesh.models.faceformer.model import FaceFormer, FaceFormerConfig
    from talkmesh.models.official import SUBJECTS
    from talkmesh.models.speech import SpeechEncoderConfig

    speech = SpeechEncoderConfig(
        kind="wav2vec2", frame_rate=30.0, resample="cnn", normalize=True, hf_config=wav2vec2_base()
    )
    cfg = FaceFormerConfig(
        num_vertices=5023,
        styles=SUBJECTS["vocaset"],
        motion_fps=30.0,
        d_model=64,
        heads=4,
        ff=128,
        layers=1,
        period=30,
        speech=speech,
        attention_window=600,
        postnorm=True,
        interleaved_ppe=True,
    )
    return FaceFormer(cfg), "fast"


def meshtalk_released():
    from talkmesh.models.meshtalk import official
    from talkmesh.models.meshtalk.model import MeshTalkModel

    def shaped(*shape):
        return SimpleNamespace(shape=shape)

    H, C, V = 16, 128, 6172
    parts = {
        "encoder.pkl": {
            "fusion_model.mlp.4.weight": shaped(H * C, 1),
            "audio_encoder.code.weight": shaped(128, 1),
            "expression_encoder.code.weight": shaped(128, 1),
        },
        "context_model.pkl": {"embedding.masked_linear.weight": shaped(H * official.HIDDEN, H * C)},
        "vertex_unet.pkl": {"mean": shaped(1, V, 3)},
    }
    cfg = official._configs(parts, 30.0, 0, Path("released"))
    return MeshTalkModel(cfg), "fast"


def bundled_synth():
    from talkmesh.models.release import load_model

    return load_model("codetalker-synth"), "chunks"


BUILDERS = {
    "codetalker": codetalker_paper,
    "faceformer": faceformer_paper,
    "meshtalk": meshtalk_released,
    "synth": bundled_synth,
}


def _spin() -> None:
    while True:
        pass


class Load:
    """One spinning process per core while inside (``on=False``: nothing)."""

    def __init__(self, on: bool) -> None:
        self.on, self.procs = on, []

    def __enter__(self):
        if self.on:
            ctx = mp.get_context("spawn")
            self.procs = [ctx.Process(target=_spin, daemon=True) for _ in range(usable_cpus())]
            for p in self.procs:
                p.start()
            time.sleep(1.0)
        return self

    def __exit__(self, *exc) -> None:
        for p in self.procs:
            p.terminate()
            p.join()


def timed_generate(net, mode: str, audio, template, kwargs: dict, policy: bool) -> float:
    if policy:
        os.environ.pop(ENV, None)
    else:
        os.environ[ENV] = "0"
    start = time.perf_counter()
    with torch.inference_mode():
        if mode == "chunks":
            for _ in net.generate_chunks(audio, template, **kwargs):
                pass
        else:
            net.generate(audio, template, mode=mode, **kwargs)
    return time.perf_counter() - start


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--seconds", type=float, default=2.0, help="speech per generate call")
    p.add_argument("--families", nargs="+", choices=FAMILIES, default=list(FAMILIES))
    args = p.parse_args()
    speech = load_audio(SPEECH)
    n = int(args.seconds * 16000)
    wave = np.tile(speech, -(-n // len(speech)))[:n]
    audio = torch.from_numpy(wave)[None]
    threads = torch.get_num_threads()
    print(
        f"# {usable_cpus()} cores, PyTorch default threads {threads}, policy: step loops on "
        f"{STEP_THREADS}; load average before: {os.getloadavg()[0]:.1f}; {args.seconds:g} s of speech"
    )
    print("| family | machine | default threads (s) | policy (s) | speed-up |")
    print("|---|---|---|---|---|")
    for family in args.families:
        torch.manual_seed(0)
        net, mode = BUILDERS[family]()
        net.eval()
        k = len(net.styles)
        kwargs = {"style_weights": torch.full((1, k), 1 / k)} if k else {}
        template = torch.zeros(1, net.num_vertices, 3)
        short = audio[:, :16000]
        timed_generate(net, mode, short, template, kwargs, policy=True)  # warm-up
        for busy in (False, True):
            with Load(busy):
                default = timed_generate(net, mode, audio, template, kwargs, policy=False)
                chosen = timed_generate(net, mode, audio, template, kwargs, policy=True)
            torch.set_num_threads(threads)
            state = "busy (1 spinner per core)" if busy else "as is"
            print(
                f"| {family} | {state} | {default:.2f} | {chosen:.2f} | {default / chosen:.2f}x |",
                flush=True,
            )


if __name__ == "__main__":
    main()
