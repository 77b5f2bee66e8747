"""Tiny datasets in the official layouts, written by the tests themselves."""

from __future__ import annotations

import pickle
from pathlib import Path

import numpy as np
import soundfile as sf

from talkmesh.datasets.reader import BIWI, VOCASET

# a wav2vec2 of two convolutions and one transformer layer, for speech="wav2vec2"
TINY_WAV2VEC2 = dict(
    hidden_size=16,
    num_hidden_layers=1,
    num_attention_heads=2,
    intermediate_size=32,
    conv_dim=(8, 8),
    conv_stride=(5, 64),
    conv_kernel=(10, 64),
    num_feat_extract_layers=2,
    num_conv_pos_embeddings=4,
    num_conv_pos_embedding_groups=2,
)

# a random Whisper encoder small enough for tests (speech.hf_config)
TINY_WHISPER = dict(
    d_model=16,
    encoder_layers=1,
    encoder_attention_heads=2,
    encoder_ffn_dim=32,
    decoder_layers=1,
    decoder_attention_heads=2,
    decoder_ffn_dim=32,
    num_mel_bins=80,
    max_source_positions=1500,
    vocab_size=64,
)


def write_wav(path: Path, seconds: float, sr: int) -> None:
    t = np.arange(int(round(seconds * sr))) / sr
    sf.write(path, (0.1 * np.sin(2 * np.pi * 220 * t)).astype(np.float32), sr)


def write_ply(path: Path, num_vertices: int) -> None:
    """An ASCII PLY with a triangle fan over the vertices."""
    faces = [(0, k, k + 1) for k in range(1, num_vertices - 1)]
    lines = [
        "ply",
        "format ascii 1.0",
        f"element vertex {num_vertices}",
        "property float x",
        "property float y",
        "property float z",
        f"element face {len(faces)}",
        "property list uchar int vertex_indices",
        "end_header",
    ]
    lines += [f"{k * 0.01} {np.sin(k)} {np.cos(k)}" for k in range(num_vertices)]
    lines += [f"3 {a} {b} {c}" for a, b, c in faces]
    path.write_text("\n".join(lines) + "\n")


def make_dataset(
    root: Path,
    spec,
    names: list[str],
    frames: int,
    disk_fps: float,
    sr: int,
    dtype=np.float32,
    python2_pickle: bool = False,
) -> dict[str, np.ndarray]:
    """Write sequences for ``names`` (<SUBJECT>_<SENTENCE>) in the contract layout."""
    v = spec.num_vertices
    (root / "wav").mkdir(parents=True, exist_ok=True)
    (root / "vertices_npy").mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(0)
    subjects = sorted({n.rpartition("_")[0] for n in names})
    templates = {s: rng.standard_normal((v, 3)).astype(np.float64) for s in subjects}
    for name in names:
        subject = name.rpartition("_")[0]
        motion = templates[subject][None] + 0.01 * rng.standard_normal((frames, v, 3))
        np.save(root / "vertices_npy" / f"{name}.npy", motion.reshape(frames, -1).astype(dtype))
        write_wav(root / "wav" / f"{name}.wav", frames / disk_fps, sr)
    if python2_pickle:
        # VOCASET's templates.pkl was written by Python 2: str keys as bytes, read with latin1
        data = {s.encode(): t for s, t in templates.items()}
    else:
        data = templates
    with open(root / "templates.pkl", "wb") as f:
        pickle.dump(data, f, protocol=2)
    write_ply(root / (spec.faces_file or "faces.ply"), v)
    return templates


def vocaset_names(missing: int = 3) -> list[str]:
    names = [
        f"{s}_{n}" for split in VOCASET.splits.values() for s, sents in split.items() for n in sents
    ]
    names = sorted(set(names))
    return names[missing:]  # the first few pairs are missing, like the real data


def make_vocaset(root: Path, frames: int = 4) -> list[str]:
    names = vocaset_names()
    make_dataset(root, VOCASET, names, frames, disk_fps=60, sr=22050, python2_pickle=True)
    return names


def make_biwi(root: Path, frames: int = 2) -> list[str]:
    """Every subject of every split, with the first and last sentence of each split's range
    (23370 vertices in float64 make the full set 450 MB; the rest count as missing pairs)."""
    names = sorted(
        {
            f"{s}_{n}"
            for split in BIWI.splits.values()
            for s, sents in split.items()
            for n in (sents[0], sents[-1])
        }
    )
    make_dataset(root, BIWI, names, frames, disk_fps=25, sr=44100, dtype=np.float64)
    (root / "regions").mkdir()
    (root / "regions" / "lve.txt").write_text(",".join(map(str, range(0, 4996))))
    (root / "regions" / "fdd.txt").write_text(", ".join(map(str, range(5000, 12784))) + "\n")
    return names


def procedural_head(rings: int = 32, segments: int = 48) -> tuple[np.ndarray, np.ndarray]:
    """A head-sized ellipsoid with a nose -> (V, 3) float32 vertices, (F, 3) outward faces."""
    theta = np.linspace(0, np.pi, rings + 1)[1:-1]
    phi = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    ring = np.stack([np.sin(t) * np.sin(p), np.cos(t), np.sin(t) * np.cos(p)], -1).reshape(-1, 3)
    v = np.concatenate([[[0, 1, 0]], ring, [[0, -1, 0]]]) * [0.08, 0.12, 0.10]
    nose = 0.03 * np.exp(-((v[:, 0] / 0.018) ** 2) - ((v[:, 1] + 0.01) / 0.03) ** 2)
    v[:, 2] += nose * (v[:, 2] > 0)
    idx = 1 + np.arange((rings - 1) * segments).reshape(rings - 1, segments)
    nxt = np.roll(idx, -1, axis=1)
    faces = [np.stack([np.zeros(segments, int), idx[0], nxt[0]], 1)]
    for r in range(rings - 2):
        faces += [np.stack([idx[r], idx[r + 1], nxt[r]], 1)]
        faces += [np.stack([nxt[r], idx[r + 1], nxt[r + 1]], 1)]
    faces += [np.stack([np.full(segments, len(v) - 1), nxt[-1], idx[-1]], 1)]
    return v.astype(np.float32), np.concatenate(faces).astype(np.int32)
