"""Models imported from the papers' released weights compute what the official code computes.

The fixtures (tests/fixtures/official/) are tiny official models with random weights, saved as the
official trainers save them, and the official prediction on speech.wav; they are made by
``scripts/make_official_fixtures.py --official PATH`` from a local checkout of the official code.
"""

from __future__ import annotations

import os
import pickle
import re
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("transformers")

from talkmesh.audio.loading import load_audio  # noqa: E402
from talkmesh.cli import main  # noqa: E402
from talkmesh.errors import TalkmeshError  # noqa: E402
from talkmesh.models.official import import_checkpoint, load_checkpoint  # noqa: E402
from talkmesh.models.postnorm import PostNormDecoderLayer, interleaved_encoding  # noqa: E402
from talkmesh.models.release import load_model  # noqa: E402

FIXTURES = Path(__file__).parent / "fixtures" / "official"
TOLERANCE = 1e-4  # of the motion's scale


def fixture(name: str) -> dict[str, np.ndarray]:
    with np.load(FIXTURES / f"{name}.npz", allow_pickle=False) as f:
        return {k: f[k] for k in f.files}


def compare(model, name: str, mode: str) -> float:
    """max |talkmesh - official| / max |official motion| on the fixture's speech."""
    fx = fixture(name)
    audio = torch.from_numpy(load_audio(FIXTURES / "speech.wav"))[None]
    template = torch.from_numpy(fx["template"])[None]
    style = list(model.styles).index(str(fx["condition"]))
    out = model.generate(audio, template, styles=torch.tensor([style]), mode=mode)[0].numpy()
    ref = fx["vertices"]
    assert out.shape == ref.shape  # same frame count
    scale = np.abs(ref - fx["template"]).max()
    assert scale > 0.1  # the official output moves: the comparison is not trivially equal
    return float(np.abs(out - ref).max() / scale)


@pytest.mark.parametrize("dataset", ["vocaset", "biwi"])
@pytest.mark.parametrize("mode", ["naive", "fast"])
def test_faceformer_import_equals_official(dataset, mode):
    model = import_checkpoint([FIXTURES / f"faceformer_{dataset}.pth"], "faceformer", dataset)
    assert model.motion_fps == {"vocaset": 30, "biwi": 25}[dataset]
    assert str(fixture(f"faceformer_{dataset}")["subjects"][0]) == model.styles[0]
    assert compare(model, f"faceformer_{dataset}", mode) <= TOLERANCE


def codetalker_files(dataset: str) -> list[Path]:
    return [FIXTURES / f"codetalker_{dataset}_stage{n}.pth.tar" for n in (1, 2)]


@pytest.mark.parametrize("dataset", ["vocaset", "biwi"])
def test_codetalker_import_equals_official(dataset):
    model = import_checkpoint(codetalker_files(dataset)[::-1], "codetalker", dataset)  # any order
    assert model.motion_fps == {"vocaset": 30, "biwi": 25}[dataset]
    # the official loop; the same with stage-2 caches; fast, which InstanceNorm makes exact
    for mode in ("naive", "exact", "fast"):
        assert compare(model, f"codetalker_{dataset}", mode) <= TOLERANCE


def test_codetalker_needs_both_files(tmp_path):
    stage1, stage2 = codetalker_files("vocaset")
    with pytest.raises(TalkmeshError, match="stage-1 .*is missing"):
        import_checkpoint([stage2, stage2], "codetalker", "vocaset")
    with pytest.raises(TalkmeshError, match="needs both released files.*stage-2 .*is missing"):
        import_checkpoint([stage1], "codetalker", "vocaset")
    with pytest.raises(TalkmeshError, match="needs both released files.*stage-1 .*is missing"):
        import_checkpoint([stage2], "codetalker", "vocaset")
    with pytest.raises(TalkmeshError, match="is --dataset right"):
        import_checkpoint([stage1, stage2], "codetalker", "biwi")


def test_cli_import_writes_a_release(tmp_path, capsys):
    out = tmp_path / "ff.safetensors"
    src = FIXTURES / "faceformer_biwi.pth"
    args = ["import-checkpoint", str(src), "--family", "faceformer", "--dataset", "BIWI"]
    assert main([*args, "-o", str(out)]) == 0
    assert "25 fps" in capsys.readouterr().out
    model = load_model(out)
    assert model.styles == ("F2", "F3", "F4", "M3", "M4", "M5")
    assert compare(model, "faceformer_biwi", "fast") <= TOLERANCE
    assert main([*args, "-o", str(out)]) == 2  # never overwritten without --overwrite
    assert "already exists" in capsys.readouterr().err


def test_prefixed_checkpoint_from_dataparallel(tmp_path):
    state = torch.load(FIXTURES / "faceformer_vocaset.pth", weights_only=True)
    path = tmp_path / "prefixed.pth"
    torch.save({"state_dict": {"module." + k: v for k, v in state.items()}}, path)
    model = import_checkpoint([path], "faceformer", "vocaset")
    assert compare(model, "faceformer_vocaset", "fast") <= TOLERANCE


class Payload:
    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


def test_malicious_checkpoint_never_runs(tmp_path):
    marker = tmp_path / "pwned"
    path = tmp_path / "evil.pth"
    with open(path, "wb") as f:
        pickle.dump({"state_dict": Payload(marker)}, f)
    torch.save({"w": torch.zeros(1), "x": Payload(marker)}, tmp_path / "evil2.pth")
    for p in (path, tmp_path / "evil2.pth"):
        with pytest.raises(TalkmeshError) as e:
            load_checkpoint(p)
        assert "\n" not in str(e.value) and "refused" in str(e.value)
    assert not marker.exists()


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda s: s.pop("vertice_map_r.bias"), "vertice_map_r.bias' is missing"),
        (lambda s: s.update(extra=torch.zeros(2)), "unexpected tensor 'extra'"),
        (lambda s: s.update({"vertice_map_r.bias": torch.zeros(5)}), "'out.bias' has shape"),
        (lambda s: s.pop("obj_vector.weight"), "not a FaceFormer checkpoint"),
    ],
)
def test_checkpoint_that_does_not_fit_is_named(tmp_path, edit, message):
    state = torch.load(FIXTURES / "faceformer_vocaset.pth", weights_only=True)
    edit(state)
    torch.save(state, tmp_path / "bad.pth")
    with pytest.raises(TalkmeshError, match=message):
        import_checkpoint([tmp_path / "bad.pth"], "faceformer", "vocaset")


def test_wrong_dataset_and_missing_files_are_named(tmp_path):
    with pytest.raises(TalkmeshError, match="is --dataset right"):
        import_checkpoint([FIXTURES / "faceformer_vocaset.pth"], "faceformer", "biwi")
    with pytest.raises(TalkmeshError, match="no such checkpoint"):
        import_checkpoint([tmp_path / "none.pth"], "faceformer", "vocaset")
    (tmp_path / "junk.pth").write_bytes(b"not a checkpoint")
    with pytest.raises(TalkmeshError, match="refused: a plain Python pickle"):
        import_checkpoint([tmp_path / "junk.pth"], "faceformer", "vocaset")


def test_postnorm_layer_is_torch_decoder_layer_with_alignment_mask():
    torch.manual_seed(0)
    d, heads, T, k = 16, 4, 7, 2
    ours = PostNormDecoderLayer(d, heads, 2 * d).eval()
    ref = torch.nn.TransformerDecoderLayer(d, heads, 2 * d, batch_first=True).eval()
    ref.load_state_dict(ours.state_dict())
    x, memory = torch.randn(1, T, d), torch.randn(1, T * k, d)
    bias = torch.randn(heads, T, T).masked_fill(torch.ones(T, T).triu(1).bool(), float("-inf"))
    aligned = torch.ones(T, T * k, dtype=torch.bool)
    for t in range(T):
        aligned[t, t * k : t * k + k] = False  # frame t sees its own k tokens
    want = ref(x, memory, tgt_mask=bias, memory_mask=aligned)
    got = ours(x, bias[None], None, memory.view(1, T, k, d))
    assert torch.allclose(got, want, atol=1e-5)


def test_interleaved_encoding_is_periodic():
    pe = interleaved_encoding(70, 8, 30)
    assert torch.equal(pe[:30], pe[30:60])
    assert torch.allclose(
        pe[1, 0::2], torch.sin(torch.tensor(1.0) * 10000 ** (-torch.arange(0, 8, 2) / 8))
    )


def test_imported_models_count_frames_as_the_official_code():
    samples = len(load_audio(FIXTURES / "speech.wav"))
    counts = {}
    for dataset in ("vocaset", "biwi"):
        model = import_checkpoint([FIXTURES / f"faceformer_{dataset}.pth"], "faceformer", dataset)
        counts[dataset] = len(fixture(f"faceformer_{dataset}")["vertices"])
        assert model.default_frames(samples) == counts[dataset]  # what animate generates
    assert counts["vocaset"] == 38 != round(samples / 16000 * 30)  # not the duration's 39


@pytest.mark.parametrize("dataset", ["vocaset", "biwi"])
def test_training_on_own_predictions_is_the_official_training_loop(dataset):
    """The official trainer's pass (``teacher_forcing=False``) runs its predict loop on the
    sequence's frame count, then the MSE: without dropout (eval), talkmesh's loop on the imported
    model gives the official output and that loss."""
    from talkmesh.training.faceformer import own_predictions
    from talkmesh.training.trainer import TorchBatch

    model = import_checkpoint([FIXTURES / f"faceformer_{dataset}.pth"], "faceformer", dataset)
    fx = fixture(f"faceformer_{dataset}")
    audio = torch.from_numpy(load_audio(FIXTURES / "speech.wav"))[None]
    ref, template = fx["vertices"], torch.from_numpy(fx["template"])
    T = len(ref)
    target = torch.from_numpy(ref)[None] + 0.01 * torch.randn(1, *ref.shape)
    style = torch.tensor([list(model.styles).index(str(fx["condition"]))])
    lengths = torch.tensor([audio.shape[1]])
    mask = torch.ones(1, T, dtype=torch.bool)
    batch = TorchBatch(["x"], audio, lengths, target, template[None], mask, style)
    with torch.no_grad():
        pred, loss = own_predictions(model.eval(), batch)
    ours = pred[0].view(T, -1, 3).numpy() + fx["template"]
    scale = np.abs(ref - fx["template"]).max()
    assert np.abs(ours - ref).max() / scale <= TOLERANCE
    want = (torch.from_numpy(ref)[None] - target).pow(2).mean()
    assert loss.item() == pytest.approx(want.item(), rel=1e-4)


@pytest.mark.slow  # 26 s of speech through the generation loops
@pytest.mark.parametrize(
    "family, dataset, modes",
    [
        ("faceformer", "vocaset", ("fast", "naive")),
        ("faceformer", "biwi", ("fast", "naive")),
        ("codetalker", "vocaset", ("exact",)),
        ("codetalker", "biwi", ("exact",)),
    ],
)
def test_imported_models_run_past_the_official_600_frames(family, dataset, modes):
    """The official code stops at 600 frames (26 s here is 780 frames at 30 fps, 650 at 25):
    talkmesh attends over the last 600 frames, and the motion stays like the motion before."""
    files = [f"faceformer_{dataset}.pth"] if family == "faceformer" else None
    paths = [FIXTURES / f for f in files] if files else codetalker_files(dataset)
    model = import_checkpoint(paths, family, dataset)
    clip = load_audio(FIXTURES / "speech.wav")
    audio = torch.from_numpy(np.tile(clip, int(np.ceil(26 * 16000 / len(clip))))[: 26 * 16000])
    template = torch.from_numpy(fixture(f"{family}_{dataset}")["template"])
    frames = model.default_frames(len(audio))
    assert frames > 600
    outs = [
        model.generate(audio[None], template[None], styles=torch.tensor([0]), mode=m)[0].numpy()
        for m in modes
    ]
    motion = outs[0] - template.numpy()
    assert outs[0].shape[0] == frames and np.isfinite(outs[0]).all()
    before, after = np.abs(motion[:600]).max(), np.abs(motion[600:]).max()
    assert 0.2 * before < after < 5 * before
    for other in outs[1:]:  # the key/value cache keeps the same 600-frame window
        assert np.abs(other - outs[0]).max() <= TOLERANCE * before


def _truncated(tmp_path: Path) -> list[Path]:
    data = (FIXTURES / "faceformer_vocaset.pth").read_bytes()
    (tmp_path / "vocaset.pth").write_bytes(data[: len(data) // 2])
    return [tmp_path / "vocaset.pth"]


def _prefixed(tmp_path: Path) -> list[Path]:
    state = torch.load(FIXTURES / "faceformer_vocaset.pth", weights_only=True)
    torch.save({"module." + k: v for k, v in state.items()}, tmp_path / "vocaset.pth")
    return [tmp_path / "vocaset.pth"]


@pytest.mark.parametrize(
    "files, family, dataset, message",
    [
        (lambda t: codetalker_files("vocaset")[1:], "codetalker", "vocaset", "both .*stage-1"),
        (lambda t: codetalker_files("vocaset")[:1], "codetalker", "vocaset", "both .*stage-2"),
        (lambda t: [FIXTURES / "faceformer_vocaset.pth"], "faceformer", "biwi", "--dataset right"),
        (lambda t: codetalker_files("biwi"), "codetalker", "vocaset", "--dataset right"),
        (lambda t: [FIXTURES / "meshtalk"], "meshtalk", "biwi", "--dataset right"),
        (_truncated, "faceformer", "vocaset", "truncated"),
        (_prefixed, "faceformer", "vocaset", None),  # DataParallel's module. prefix: imported
    ],
    ids=["ct-no-stage1", "ct-no-stage2", "ff-dataset", "ct-dataset", "mt-dataset", "cut", "module"],
)
def test_cli_import_errors_are_one_line(tmp_path, capsys, files, family, dataset, message):
    paths = [str(p) for p in files(tmp_path)]
    out = tmp_path / "out.safetensors"
    rc = main(
        ["import-checkpoint", *paths, "--family", family, "--dataset", dataset, "-o", str(out)]
    )
    err = capsys.readouterr().err
    if message is None:
        assert rc == 0 and out.exists() and not err, err
        return
    assert rc == 2 and not out.exists()
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    assert err.startswith("talkmesh: error: ") and re.search(message, err), err


def test_the_importers_are_found_in_the_family_folders(tmp_path):
    """``import_checkpoint`` calls ``<family folder>/official.py``; a registered family without
    one (VOCA released no weights we import) is named as unknown, with the ones that have it."""
    from talkmesh.models.registry import official_families

    assert official_families() == ("codetalker", "faceformer", "meshtalk")
    with pytest.raises(TalkmeshError, match="unknown family 'voca': use one of codetalker, "):
        import_checkpoint([FIXTURES / "faceformer_vocaset.pth"], "voca", "vocaset")
    with pytest.raises(TalkmeshError, match="MeshTalk's own mesh: faceformer uses vocaset or biwi"):
        import_checkpoint([FIXTURES / "faceformer_vocaset.pth"], "faceformer", "meshtalk")
    with pytest.raises(TalkmeshError, match="one file"):
        import_checkpoint([FIXTURES / "faceformer_vocaset.pth"] * 2, "faceformer", "vocaset")
    model = import_checkpoint([FIXTURES / "faceformer_vocaset.pth"], "faceformer", "VOCASET")
    assert type(model).__module__ == "talkmesh.models.faceformer.model"
