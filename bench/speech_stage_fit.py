"""How well CodeTalker's speech stage fits its own training clips, against its VQ-VAE.

    python bench/speech_stage_fit.py --data corpus/multilingual [--model codetalker-synth] [--every 25]

For every ``--every``-th training clip (its first 5 s): the lip-gap error
(:func:`talkmesh.training.lip_gap.lip_gap_loss`, per cent of the lip region's width, squared) of
the VQ-VAE's reconstruction of the truth (what the codebook can say), of the speech stage fed the
true motion (teacher forcing, as in training) and of generation from the audio alone; then the
midline lip opening of the teacher-forced prediction against the truth: its correlation, the lag
(frames) at which the correlation is best, and the smallest opening of each. A speech stage that
fits would come near the reconstruction's error; one whose best lag is not 0 hears the audio
shifted against the motion.
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from talkmesh.datasets.reader import open_dataset
from talkmesh.face.assets import load_head
from talkmesh.models.release import load_model
from talkmesh.training.lip_gap import lip_gap_loss, lip_gap_pairs, lip_width

FRAMES = 150
LAGS = range(-6, 7)


def best_lag(truth: np.ndarray, pred: np.ndarray) -> tuple[int, float, float]:
    """(lag of the best correlation, that correlation, the correlation at lag 0)."""
    n = len(truth)
    corr = {}
    for lag in LAGS:
        a, b = (truth[lag:], pred[: n - lag]) if lag >= 0 else (truth[: n + lag], pred[-lag:])
        corr[lag] = float(np.corrcoef(a, b)[0, 1])
    lag = max(corr, key=corr.get)
    return lag, corr[lag], corr[0]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", required=True, help="a synthetic or multilingual corpus")
    ap.add_argument("--model", default="codetalker-synth")
    ap.add_argument("--every", type=int, default=25, help="score every N-th training clip")
    args = ap.parse_args()
    torch.set_num_threads(1)
    data = open_dataset("synth", args.data, "train")
    lips = data.regions.lve
    pairs = torch.from_numpy(lip_gap_pairs(data, lips))
    width = lip_width(data[0].template, lips)
    upper, lower = load_head().regions.lip_pair
    net = load_model(args.model).float().eval()
    styles = list(net.cfg.stage2.styles)
    print(
        "| clip | reconstruction | teacher-forced | generated | r at lag 0 | best lag | "
        "smallest opening truth / forced (mm) |"
    )
    print("|---|---|---|---|---|---|---|")
    rows = []
    for i in range(0, len(data), args.every):
        s = data[i]
        T = min(FRAMES, len(s.vertices))
        v = torch.from_numpy(np.ascontiguousarray(s.vertices[:T]))[None]
        tpl = torch.from_numpy(s.template)[None]
        audio = torch.from_numpy(s.audio[: int(T / data.spec.motion_fps * 16000)])[None]
        style = torch.tensor([styles.index(s.subject) if s.subject in styles else -1])
        motion = (v - tpl[:, None]).flatten(2)
        with torch.no_grad():
            recon = net.vqvae(motion, None, face=net.decoder_face(tpl)).motion
            forced = net(audio, None, v, tpl, style).motion
            made = net.generate(audio, tpl, styles=style.clamp(min=0), num_frames=T)
        made = (made - tpl[:, None]).flatten(2)
        errors = [float(lip_gap_loss(m, v, tpl, pairs, width)) for m in (recon, forced, made)]
        shaped = forced.view(1, T, -1, 3) + tpl[:, None]
        truth_open = (v[0, :, upper] - v[0, :, lower]).norm(dim=-1).numpy() * 1000
        forced_open = (shaped[0, :, upper] - shaped[0, :, lower]).norm(dim=-1).numpy() * 1000
        lag, _, r0 = best_lag(truth_open, forced_open)
        rows.append((*errors, r0, lag))
        print(
            f"| {s.name} | {errors[0]:.2f} | {errors[1]:.2f} | {errors[2]:.2f} | {r0:.2f} | "
            f"{lag} | {truth_open.min():.1f} / {forced_open.min():.1f} |"
        )
    med = np.median(np.array(rows), axis=0)
    print(
        f"| median ({len(rows)} clips) | {med[0]:.2f} | {med[1]:.2f} | {med[2]:.2f} | "
        f"{med[3]:.2f} | {med[4]:.0f} | |"
    )


if __name__ == "__main__":
    main()
