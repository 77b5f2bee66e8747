"""``talkmesh evaluate`` and ``talkmesh baseline``: score predictions named like the anchors'.

Predictions are ``PRED/<SUBJECT>_<SENTENCE>.npy`` or ``..._condition_<STYLE>.npy`` (one file per
training style, as the anchors write for unseen speakers), [T, V*3] or [T, V, 3] at the dataset's
motion frame rate. Every (sequence, condition) is a row; LVE and MVE pool all their frames.
"""

from __future__ import annotations

import re
import sys
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from talkmesh.datasets.reader import MotionDataset, open_dataset, report_skipped
from talkmesh.errors import TalkmeshError
from talkmesh.evaluation.metrics import PROTOCOLS, Scores, pool, score_sequence
from talkmesh.face.corrections import NONE, Corrections

CONDITION = re.compile(r"^(?P<name>.+?)_condition_(?P<style>.+)$")


def find_predictions(
    pred_dir: str | Path, names: list[str]
) -> dict[str, list[tuple[str | None, Path]]]:
    """Prediction files per sequence name: [(condition or None, path), ...]."""
    pred_dir = Path(pred_dir)
    if not pred_dir.is_dir():
        raise TalkmeshError(f"predictions directory not found: {pred_dir}")
    wanted = set(names)
    found: dict[str, list[tuple[str | None, Path]]] = {}
    for path in sorted(pred_dir.glob("*.npy")):
        stem = path.stem
        m = CONDITION.match(stem)
        name, cond = (m["name"], m["style"]) if m else (stem, None)
        if name in wanted:
            found.setdefault(name, []).append((cond, path))
    return found


def _load_prediction(path: Path, num_vertices: int) -> np.ndarray:
    try:
        arr = np.load(path, allow_pickle=False)
    except (ValueError, OSError, EOFError) as e:
        raise TalkmeshError(f"{path}: not a readable .npy ({e})") from None
    if arr.ndim == 2 and arr.shape[1] == num_vertices * 3:
        arr = arr.reshape(len(arr), num_vertices, 3)
    if arr.ndim != 3 or arr.shape[1:] != (num_vertices, 3):
        raise TalkmeshError(
            f"{path}: shape {arr.shape} does not match the dataset's {num_vertices} vertices "
            f"(expected [T, {num_vertices * 3}])"
        )
    return arr.astype(np.float32)


def bundled_lip_pairs(num_vertices: int) -> np.ndarray | None:
    """The bundled head's (P, 2) upper/lower inner-lip vertex pairs, or None when a mesh of
    ``num_vertices`` is another topology (its lip pairs are unknown: no lip-sync score)."""
    from talkmesh.face.assets import load_head

    head = load_head()
    if num_vertices == head.num_vertices:
        return np.asarray(head.regions.lip_pair).reshape(-1, 2)
    return None


def evaluate_dataset(
    dataset: MotionDataset,
    pred: str | Path,
    *,
    protocol: str = "codetalker",
) -> tuple[Scores, list[str]]:
    """Scores of the predictions in ``pred`` on ``dataset``, and the sequences without one."""
    if protocol not in PROTOCOLS:
        raise TalkmeshError(f"unknown protocol '{protocol}': use one of {', '.join(PROTOCOLS)}")
    if dataset.regions.lve is None or dataset.regions.fdd is None:
        raise TalkmeshError(
            f"{dataset.root}: no regions/lve.txt and regions/fdd.txt: pass --regions DIR"
        )
    found = find_predictions(pred, dataset.names)
    if not found:
        raise TalkmeshError(
            f"{pred}: no prediction named like a {dataset.split} sequence "
            f"(e.g. {dataset.names[0] + '.npy' if dataset.names else '<SUBJECT>_<SENTENCE>.npy'})"
        )
    pending, missing = [], []
    for index, name in enumerate(dataset.names):
        if name not in found:
            missing.append(name)
            continue
        try:
            sample = dataset[index]
        except TalkmeshError as e:  # one bad ground-truth file does not stop the evaluation
            dataset.reject(name, str(e))
            continue
        pairs = bundled_lip_pairs(len(sample.template))
        for cond, path in found[name]:
            p = _load_prediction(path, len(sample.template))
            pending.append(
                score_sequence(
                    p,
                    sample.vertices,
                    sample.template,
                    dataset.regions.lve,
                    dataset.regions.fdd,
                    protocol,
                    pairs,
                    name,
                    cond,
                )
            )
    if not pending:
        raise TalkmeshError(f"{dataset.root}: no {dataset.split} sequence could be scored")
    return pool(pending, protocol), missing


def evaluate(
    kind: str,
    data: str | Path,
    pred: str | Path,
    *,
    split: str = "test",
    protocol: str = "codetalker",
    regions: str | Path | None = None,
) -> Scores:
    """``talkmesh evaluate``: open the dataset split and score the predictions."""
    dataset = open_dataset(kind, data, split, regions=regions)
    scores, _ = evaluate_dataset(dataset, pred, protocol=protocol)
    report_skipped(dataset, "evaluation")
    return scores


# the table's metric columns per protocol: (header, Scores field, scale, decimals)
TABLE_COLUMNS = {
    "codetalker": (
        ("LVE (x1e-4, squared)", "lve", 1e4, 4),
        ("FDD (x1e-5, signed)", "fdd", 1e5, 4),
        ("MVE (mm)", "mve", 1e3, 3),
    ),
    "physical": (
        ("LVE (mm)", "lve", 1e3, 3),
        ("FDD (mm, absolute)", "fdd", 1e3, 4),
        ("MVE (mm)", "mve", 1e3, 3),
    ),
}


def format_table(scores: Scores, label: str = "") -> str:
    """A one-row table in the papers' units (anchor protocol) or in mm (physical)."""
    columns = TABLE_COLUMNS.get(scores.protocol, TABLE_COLUMNS["physical"])
    heads = ["method", *(c[0] for c in columns), "lip-sync r", "seqs", "frames"]
    cells = [label or "-", *(f"{getattr(scores, k) * scale:.{d}f}" for _, k, scale, d in columns)]
    cells += [f"{scores.lip_sync:.3f}", str(scores.n_sequences), str(scores.n_frames)]
    return "\n".join(
        [
            "| " + " | ".join(heads) + " |",
            "|" + "---|" * len(heads),
            "| " + " | ".join(cells) + " |",
        ]
    )


def scores_to_json(scores: Scores, split: str | None = None) -> dict:
    """The scores as written by ``talkmesh evaluate --json`` and the benchmark: the pooled values
    and one row per (sequence, condition); NaN lip sync becomes null."""
    return {
        "protocol": scores.protocol,
        "split": split,
        "lve": scores.lve,
        "fdd": scores.fdd,
        "mve": scores.mve,
        "lip_sync": None if np.isnan(scores.lip_sync) else scores.lip_sync,
        "n_sequences": scores.n_sequences,
        "n_frames": scores.n_frames,
        "rows": [
            {
                "name": r.name,
                "condition": r.condition,
                "frames": r.frames,
                "truncated": r.truncated,
                "lve": r.lve,
                "fdd": r.fdd,
                "mve": r.mve,
                "lip_sync": None if np.isnan(r.lip_sync) else r.lip_sync,
            }
            for r in scores.rows
        ],
    }


def write_baseline(
    kind: str,
    data: str | Path,
    out_dir: str | Path,
    *,
    method: str = "static",
    split: str = "test",
    progress: bool = True,
) -> int:
    """Write baseline predictions for a split: ``static`` (the template, unmoving) or
    ``procedural`` (phones RECOGNISED from the audio -> procedural lip sync with the default
    style on the subject's head; no learning and no true timings)."""
    import json

    from tqdm import tqdm

    if method not in ("static", "procedural"):
        raise TalkmeshError(f"unknown baseline '{method}': use static or procedural")
    dataset = open_dataset(kind, data, split)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    identities: dict[str, str] = {}
    if method == "procedural":
        manifest = Path(data) / "manifest.json"
        if not manifest.is_file():
            raise TalkmeshError(
                f"the procedural baseline needs blendshapes for the subjects: {kind} data at {data} has "
                "no manifest.json naming talkmesh identities (use --method static)"
            )
        identities = {
            s: m["identity"] for s, m in json.loads(manifest.read_text())["subjects"].items()
        }
    written = 0
    for index in tqdm(range(len(dataset)), desc=method, unit="seq", disable=not progress):
        try:
            sample = dataset[index]
        except TalkmeshError as e:  # one bad file does not stop the run
            dataset.reject(dataset.names[index], str(e))
            continue
        path = out / f"{sample.name}.npy"
        if path.exists():
            raise TalkmeshError(f"{path} already exists: choose an empty output directory")
        if method == "static":
            pred = np.repeat(sample.template[None], len(sample.vertices), axis=0)
        else:
            from talkmesh.audio.loading import SAMPLE_RATE
            from talkmesh.audio.phonemes import recognize_phones
            from talkmesh.face.assets import load_head
            from talkmesh.face.lipsync import phones_to_weights

            head = load_head(identities[sample.subject]).with_template(
                sample.template, sample.subject
            )
            phones = recognize_phones(sample.audio, SAMPLE_RATE)
            weights = phones_to_weights(
                phones,
                len(sample.vertices),
                dataset.spec.motion_fps,
                audio=sample.audio,
                sr=SAMPLE_RATE,
            )
            pred = head.vertices_from_weights(weights)
        np.save(path, pred.reshape(len(pred), -1).astype(np.float32))
        written += 1
    return _written(written, dataset, "baseline")


RECONSTRUCT = "reconstruct"  # write_model_predictions(mode=): the model's motion autoencoder alone


def _prediction_jobs(sample, styles: list[str], conditions: bool) -> list[tuple[str, Any]]:
    """(file name, (K,) style weights or None) of each prediction of ``sample`` (see
    :func:`write_model_predictions`)."""
    import torch

    def one_hot(k: int):
        return torch.nn.functional.one_hot(torch.tensor(k), len(styles)).float()

    if not styles:  # no speaker conditioning
        return [(f"{sample.name}.npy", None)]
    if sample.subject in styles:
        return [(f"{sample.name}.npy", one_hot(styles.index(sample.subject)))]
    if conditions:
        return [(f"{sample.name}_condition_{s}.npy", one_hot(k)) for k, s in enumerate(styles)]
    return [(f"{sample.name}.npy", torch.full((len(styles),), 1.0 / len(styles)))]


def write_model_predictions(
    kind: str,
    data: str | Path,
    out_dir: str | Path,
    model: str,
    *,
    split: str = "test",
    conditions: bool = False,
    mode: str = "fast",
    blinks: bool = False,
    pause_gate: bool = False,
    corrections: bool = False,
    progress: bool = True,
) -> int:
    """Predictions of a learned model (a release file or bundled name) for a split.

    With ``corrections``, the mouth is corrected by the phone recogniser as ``talkmesh animate``
    does by default (:mod:`talkmesh.face.corrections`); with ``pause_gate`` only closed in the
    pauses it finds (bundled head topology only).

    With ``blinks``, the model's own eye motion is replaced by the procedural animator's blinks
    and gaze (seeded by the sequence index), through the bundled head's blendshapes, as
    ``talkmesh animate`` does.

    Speakers seen in training use their own style. Unseen speakers get the mean of the training
    styles (``SUBJECT_SENTENCE.npy``) or, with ``conditions``, one prediction per training style
    (``SUBJECT_SENTENCE_condition_STYLE.npy``), as the anchors evaluate them.
    """
    from tqdm import tqdm

    from talkmesh.models.release import load_model

    net = load_model(model)
    styles = list(net.styles)
    dataset = open_dataset(kind, data, split)
    if net.num_vertices != len(dataset.templates[next(iter(dataset.templates))]):
        raise TalkmeshError(f"model {model} and the {kind} data at {data} differ in vertex count")
    if mode != RECONSTRUCT:
        net.check_mode(mode)
    note = net.mode_note(mode)
    if progress and note:
        print(f"talkmesh: note: {note}", file=sys.stderr)
    fix = Corrections() if corrections else replace(NONE, pause_gate=pause_gate)
    finish = _finisher(net.num_vertices, dataset.spec.motion_fps, blinks, fix, _identities(data))
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written = 0

    for index in tqdm(range(len(dataset)), desc="predict", unit="seq", disable=not progress):
        try:
            sample = dataset[index]
        except TalkmeshError as e:  # one bad file does not stop the run
            dataset.reject(dataset.names[index], str(e))
            continue
        for filename, weights in _prediction_jobs(sample, styles, conditions):
            path = out / filename
            if path.exists():
                raise TalkmeshError(f"{path} already exists: choose an empty output directory")
            verts = _generate(net, sample, weights, index, mode)
            finish(verts, sample, index)
            np.save(path, verts.reshape(len(verts), -1).astype(np.float32))
            written += 1
    return _written(written, dataset, "predict")


def _generate(net, sample, weights, seed: int, mode: str) -> np.ndarray:
    """One prediction (T, V, 3) of ``sample``: generated from its audio, or with
    :data:`RECONSTRUCT` its motion through the model's autoencoder."""
    import torch

    with torch.inference_mode():
        template = torch.from_numpy(sample.template)[None]
        if mode == RECONSTRUCT:  # the motion autoencoder alone: what its codes keep
            vertices = torch.tensor(sample.vertices)[None]
            return net.reconstruct(vertices, template)[0].numpy()
        return net.generate(
            torch.from_numpy(sample.audio)[None],
            template,
            style_weights=None if weights is None else weights[None],
            num_frames=len(sample.vertices),
            seed=seed,
            mode=mode,
        )[0].numpy()


def _identities(data: str | Path) -> dict[str, str]:
    """subject -> talkmesh identity, from a synthetic corpus's manifest (else empty)."""
    import json

    manifest = Path(data) / "manifest.json"
    if not manifest.is_file():
        return {}
    subjects = json.loads(manifest.read_text()).get("subjects", {})
    return {s: m["identity"] for s, m in subjects.items() if "identity" in m}


def _finisher(
    num_vertices: int, fps: float, blinks: bool, fix: Corrections, identities: dict[str, str]
):
    """``finish(verts, sample, index)``, changing a prediction in place as ``talkmesh animate``
    does: the mouth corrected by the phone recogniser, the model's eye motion replaced by
    procedural blinks and gaze. Both need the bundled head's topology (a one-line error now);
    the procedural mouth is made with the subject's identity's blendshapes (``identities``),
    else the bundled default identity's."""
    from talkmesh.face.assets import load_head

    if blinks:
        from talkmesh.face.arkit import fit_weights
        from talkmesh.face.lipsync import blink_gaze_weights, replace_eye_motion

        head = load_head()
        if head.num_vertices != num_vertices:
            raise TalkmeshError("blinks need the bundled head's topology (its blendshapes)")
        basis = head.blendshapes.reshape(len(head.blendshape_names), -1)
    if fix != NONE:
        from talkmesh.audio.loading import SAMPLE_RATE
        from talkmesh.audio.phonemes import recognize_phones
        from talkmesh.face.corrections import correct_mouth

        if load_head().num_vertices != num_vertices:
            raise TalkmeshError("the corrections need the bundled head's topology (its mouth map)")

    def finish(verts: np.ndarray, sample, index: int) -> None:
        if fix != NONE:  # as animate: the recogniser corrects the mouth
            phones = recognize_phones(sample.audio, SAMPLE_RATE)
            face = load_head(identities.get(sample.subject)).with_template(
                sample.template, sample.subject
            )
            correct_mouth(verts, face, phones, sample.audio, fps, fix)
        if blinks:  # as animate: the model's own eye motion becomes procedural eyes
            eyes = blink_gaze_weights(len(verts), fps, seed=index)
            fitted = fit_weights(verts, head.blendshapes, sample.template)
            replace_eye_motion(verts, fitted, eyes, basis)

    return finish


def _written(written: int, dataset: MotionDataset, action: str) -> int:
    """A run that wrote nothing is an error; one that skipped files says how many."""
    report_skipped(dataset, action)
    if written == 0:
        raise TalkmeshError(
            f"{action} wrote no predictions: all {len(dataset.bad)} sequences of the "
            f"{dataset.split} split of {dataset.root} failed to load (see the warnings)"
        )
    return written
