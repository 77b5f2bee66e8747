"""Imported paper-size models against the official code: generation time, side by side.

    python bench/official_speed.py --official-codetalker /path/to/CodeTalker \\
        --official-faceformer /path/to/FaceFormer [--seconds 4 30] [--dataset vocaset]

Each ``--official-*`` is a local checkout of the paper's code, imported at run time (none of its
code is copied here), loaded as ``scripts/make_official_fixtures.py`` loads it (wav2vec 2.0 from
``Wav2Vec2Config()`` instead of ``from_pretrained``, on the CPU). Per family:

1. builds the official model at the paper's size (FaceFormer VOCASET: d_model 64; CodeTalker
   VOCASET: the released configs' stage 1 and stage 2; wav2vec 2.0 base) with random weights
   (seeded; the zero-initialised output maps get random values so the output moves);
2. saves it as the official trainers do and imports the files with ``talkmesh import-checkpoint``'s
   function;
3. on the same speech (the fixtures' clip, repeated to each length), times the official
   ``predict`` and talkmesh's ``generate`` in each mode, one after the other in this process, and
   prints max |talkmesh - official| / max |official motion| where the official code runs.

The official code stops at 600 frames (its positional encoding and temporal bias are 600 long):
longer audio is not run through it (the row says so). talkmesh's CodeTalker ``fast`` mode is its
``exact`` mode for imported models (InstanceNorm over time needs the whole prefix), so CodeTalker
rows show ``exact`` and ``naive`` (the official loop; up to 600 frames, like the official code).
``--official-timeout S`` stops an official ``predict`` after S seconds (between two of its steps):
its row says so, and talkmesh's speed-up over it is a lower bound ("> x").
Times are wall-clock seconds of one run each (after an untimed 1 s warm-up run of each), on
``--threads`` CPU threads, or on a GPU with ``--device cuda`` (both codes on the same device;
the clock stops after ``torch.cuda.synchronize()``).
"""

from __future__ import annotations

import argparse
import importlib.util
import signal
import sys
import tempfile
import time
from functools import partial
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import torch

from talkmesh.audio.loading import load_audio
from talkmesh.models.official import MAX_FRAMES, SUBJECTS, import_checkpoint

ROOT = Path(__file__).resolve().parents[1]
SPEECH = ROOT / "tests" / "fixtures" / "official" / "speech.wav"
SEED = 0
VERTICES = {"vocaset": 5023, "biwi": 23370}


def fixture_script():
    """scripts/make_official_fixtures.py as a module (its loading helpers)."""
    path = ROOT / "scripts" / "make_official_fixtures.py"
    spec = importlib.util.spec_from_file_location("make_official_fixtures", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def official_faceformer(
    checkout: Path, dataset: str, out: Path, fx, device: str = "cpu"
) -> tuple[object, list[Path]]:
    """The official FaceFormer at the paper's size, saved as its trainer saves it."""
    from transformers import Wav2Vec2Config

    sys.path.insert(0, str(checkout))
    import faceformer as official  # the checkout's faceformer.py

    official.Wav2Vec2Model.from_pretrained = classmethod(
        lambda cls, *a, **k: cls(Wav2Vec2Config(attn_implementation="eager"))
    )
    torch.manual_seed(SEED)
    args = SimpleNamespace(
        dataset={"vocaset": "vocaset", "biwi": "BIWI"}[dataset],
        vertice_dim=VERTICES[dataset] * 3,
        feature_dim={"vocaset": 64, "biwi": 128}[dataset],
        period={"vocaset": 30, "biwi": 25}[dataset],
        train_subjects=" ".join(SUBJECTS[dataset]),
        device=device,
    )
    model = official.Faceformer(args)
    torch.nn.init.normal_(model.vertice_map_r.weight, std=0.01)  # zero-initialised officially
    model.eval()
    fx.patch_encoder(model.audio_encoder)
    path = out / f"faceformer_{dataset}.pth"
    torch.save(fx.torch1_names(model.state_dict()), path)
    sys.path.remove(str(checkout))
    return model.to(device), [path]


def official_codetalker(
    checkout: Path, dataset: str, out: Path, fx, device: str = "cpu"
) -> tuple[object, list[Path]]:
    """The official CodeTalker at the released configs' size, both stages saved as its trainers
    save them, stage 2 built from the stage-1 file as its demo builds it."""
    from transformers import Wav2Vec2Config

    sys.path.insert(0, str(checkout))
    from base.baseTrainer import save_checkpoint
    from models.lib import wav2vec
    from models.stage2 import CodeTalker

    wav2vec.Wav2Vec2Model.from_pretrained = classmethod(
        lambda cls, *a, **k: cls(Wav2Vec2Config(attn_implementation="eager"))
    )
    torch.manual_seed(SEED)
    name = {"vocaset": "vocaset", "biwi": "BIWI"}[dataset]
    H, C = {"vocaset": (16, 64), "biwi": (8, 128)}[dataset]
    args = SimpleNamespace(
        dataset=name,
        train_subjects=" ".join(SUBJECTS[dataset]),
        in_dim=VERTICES[dataset] * 3,
        hidden_size=1024,
        num_hidden_layers=6,
        num_attention_heads=8,
        intermediate_size=1536,
        window_size=1,
        quant_factor=0,
        face_quan_num=H,
        neg=0.2,
        INaffine=False,
        n_embed=256,
        zquant_dim=C,
        autoencoder=f"stage1_{name}",
        feature_dim=1024,
        vertice_dim=VERTICES[dataset] * 3,
        device=device,
        period={"vocaset": 30, "biwi": 25}[dataset],
        n_head=4,
        num_layers={"vocaset": 6, "biwi": 12}[dataset],
        wav2vec2model_path="(random)",
        motion_weight=1.0,
        reg_weight=1.0,
    )
    stage1 = __import__(f"models.stage1_{name}", fromlist=["VQAutoEncoder"])
    vq = stage1.VQAutoEncoder(args)
    torch.nn.init.normal_(vq.quantize.embedding.weight, std=0.5)  # spread like trained codes
    files = [out / f"codetalker_{dataset}_stage{n}.pth.tar" for n in (1, 2)]
    save_checkpoint(vq, {"epoch": 200}, sav_path=str(out), filename=files[0].name)
    args.vqvae_pretrained_path = str(files[0])
    model = CodeTalker(args)
    torch.nn.init.normal_(model.feat_map.weight, std=0.05)  # zero-initialised officially
    model.eval()
    fx.patch_encoder(model.audio_encoder)
    save_checkpoint(model, {"epoch": 100}, sav_path=str(out), filename=files[1].name, stage=2)
    sys.path.remove(str(checkout))
    return model.to(device), files


def timed(fn, device: str = "cpu"):
    if device != "cpu":
        torch.cuda.synchronize()
    start = time.perf_counter()
    result = fn()
    if device != "cpu":
        torch.cuda.synchronize()
    return time.perf_counter() - start, result


class Stopped(Exception):
    pass


def stopped_after(seconds: float | None, fn):
    """``fn()``, or None once ``seconds`` have passed (SIGALRM: the main thread, POSIX): the
    official loop is Python, one step at a time, so it stops between two steps."""
    if not seconds:
        return fn()

    def stop(signum, frame):
        raise Stopped

    previous = signal.signal(signal.SIGALRM, stop)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        return fn()
    except Stopped:
        return None
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


def run_family(family: str, checkout: Path, args, speech: np.ndarray, out: Path, fx) -> None:
    build = {"faceformer": official_faceformer, "codetalker": official_codetalker}[family]
    dev = args.device
    official, files = build(checkout, args.dataset, out, fx, dev)
    model = import_checkpoint(files, family, args.dataset).eval().to(dev)
    V = VERTICES[args.dataset]
    template = (torch.randn(V, 3, generator=torch.Generator().manual_seed(1)) * 0.1).to(dev)
    one_hot = torch.zeros(1, len(model.styles), device=dev)
    one_hot[0, 0] = 1
    style = torch.tensor([0], device=dev)
    modes = ("naive", "fast") if family == "faceformer" else ("naive", "exact")
    if args.skip_naive:
        modes = modes[1:]
    label = f"{family} {args.dataset}"
    # warm-up (one-time costs: thread pools, first-call allocations), not timed
    short = torch.from_numpy(speech[:16000])[None].to(dev)
    with torch.no_grad():
        official.predict(
            torch.from_numpy(fx.processor_input(speech[:16000]))[None].to(dev),
            template.reshape(1, -1),
            one_hot,
        )
    with torch.inference_mode():
        for mode in modes:
            model.generate(short, template[None], styles=style, mode=mode)
    for seconds in args.seconds:
        wave = speech[: int(seconds * 16000)]
        frames = model.default_frames(len(wave))
        ref, official_s = None, None
        if frames <= MAX_FRAMES:
            inputs = torch.from_numpy(fx.processor_input(wave))[None].to(dev)
            torch.set_num_threads(args.official_threads or args.threads)
            predict = partial(official.predict, inputs, template.reshape(1, -1), one_hot)
            with torch.no_grad():
                official_s, out_ = timed(
                    partial(stopped_after, args.official_timeout, predict), dev
                )
            torch.set_num_threads(args.threads)
            if out_ is None:  # stopped: its time is a lower bound, and there is no output
                print(
                    f"| {label} | {seconds:g} | {frames} | official predict | stopped after "
                    f"{official_s:.0f} | 1.0 | |"
                )
            else:
                ref = out_[0].reshape(-1, V, 3).cpu().numpy()
                print(
                    f"| {label} | {seconds:g} | {frames} | official predict | {official_s:.2f} "
                    "| 1.0 | |"
                )
        else:
            print(
                f"| {label} | {seconds:g} | {frames} | official predict | stops at 600 frames | | |"
            )
        sys.stdout.flush()
        for mode in modes:
            if mode == "naive" and family == "codetalker" and frames > MAX_FRAMES:
                continue  # the official loop's cost, like the official code: skipped past 600
            with torch.inference_mode():
                sec, got = timed(
                    partial(
                        model.generate,
                        torch.from_numpy(wave)[None].to(dev),
                        template[None],
                        styles=style,
                        mode=mode,
                    ),
                    dev,
                )
            got = got[0].cpu().numpy()
            diff = ""
            if ref is not None:
                scale = np.abs(ref - template.cpu().numpy()).max()
                diff = (
                    f"{np.abs(got - ref).max() / scale:.1e}"
                    if got.shape == ref.shape
                    else "frames differ"
                )
            ratio = f"{official_s / sec:.1f}" if official_s else ""
            if official_s and ref is None:  # the official run was stopped: at least this
                ratio = f"> {ratio}"
            print(
                f"| {label} | {seconds:g} | {len(got)} | talkmesh {mode} | {sec:.2f} | {ratio} | {diff} |"
            )
            sys.stdout.flush()
        if args.batch > 1:
            batch_row(model, modes[-1], wave, template, style, args.batch, official_s, ref, label)


def batch_row(model, mode, wave, template, style, n, official_s, ref, label) -> None:
    """The same clip n times in one batch: what talkmesh can do and the official code cannot."""
    dev = template.device
    sec, got = timed(
        partial(
            model.generate,
            torch.from_numpy(wave)[None].repeat(n, 1).to(dev),
            template[None].repeat(n, 1, 1),
            styles=style.repeat(n),
            mode=mode,
        ),
        str(dev.type),
    )
    got = got.cpu().numpy()
    diff, ratio = "", ""
    if ref is not None:
        scale = np.abs(ref - template.cpu().numpy()).max()
        diff = f"{np.abs(got - ref[None]).max() / scale:.1e}"
        ratio = f"{official_s * n / sec:.1f}"
    print(
        f"| {label} | {len(wave) / 16000:g} | {got.shape[1]} x {n} | talkmesh {mode}, "
        f"{n} clips in one batch | {sec:.2f} | {ratio} | {diff} |"
    )
    sys.stdout.flush()


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--official-codetalker", type=Path, help="a checkout of Doubiiu/CodeTalker")
    p.add_argument("--official-faceformer", type=Path, help="a checkout of EvelynFan/FaceFormer")
    p.add_argument("--dataset", choices=("vocaset", "biwi"), default="vocaset")
    p.add_argument("--seconds", type=float, nargs="+", default=[4.0, 30.0])
    p.add_argument("--threads", type=int, default=torch.get_num_threads())
    p.add_argument(
        "--official-threads",
        type=int,
        help="PyTorch threads of the official predict (default: --threads; talkmesh's step loops "
        "take their own, talkmesh.models.threads)",
    )
    p.add_argument("--skip-naive", action="store_true", help="do not time talkmesh's naive mode")
    p.add_argument("--device", default="cpu", help="cpu or cuda (both codes run there)")
    p.add_argument(
        "--official-timeout",
        type=float,
        help="stop an official predict after this many seconds: its row then gives a lower "
        "bound of its time (and of the speed-up), and no output to compare with",
    )
    p.add_argument(
        "--batch",
        type=int,
        default=1,
        help="also time talkmesh on this many copies of each clip in one batch "
        "(speed-up against the official code run once per clip)",
    )
    p.add_argument(
        "--workdir",
        type=Path,
        help="where the official-format files go (default: a temporary folder)",
    )
    args = p.parse_args()
    if not (args.official_codetalker or args.official_faceformer):
        p.error("give --official-codetalker and/or --official-faceformer")
    torch.set_num_threads(args.threads)
    if args.device != "cpu":
        torch.backends.cudnn.allow_tf32 = False  # float32 convolutions, as on the CPU
        torch.backends.cuda.matmul.allow_tf32 = False
    fx = fixture_script()
    clip = load_audio(SPEECH)
    speech = np.tile(clip, int(np.ceil(max(args.seconds) * 16000 / len(clip))))
    where = torch.cuda.get_device_name(0) if args.device != "cpu" else f"{args.threads} CPU threads"
    if args.device == "cpu" and args.official_threads:
        where += f" ({args.official_threads} for the official predict)"
    print(f"{where}, torch {torch.__version__}; speech: {SPEECH.name} repeated")
    print(
        "| model | audio (s) | frames | run | seconds | speed-up vs official | max diff / motion |"
    )
    print("|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        out = args.workdir or Path(tmp)
        out.mkdir(parents=True, exist_ok=True)
        for family, checkout in (
            ("faceformer", args.official_faceformer),
            ("codetalker", args.official_codetalker),
        ):
            if checkout is not None:
                run_family(family, checkout.resolve(), args, speech, out, fx)


if __name__ == "__main__":
    main()
