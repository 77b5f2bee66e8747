"""``talkmesh benchmark`` end to end on a tiny synthetic corpus: two methods (a tiny mel CodeTalker
in two stages and a tiny VOCA) x two seeds, a two-cell ablation, speed at 1 s, a tiny video;
then resume (nothing retrains) and a partial state (only the missing stages retrain)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from talkmesh.cli import main
from talkmesh.datasets.synth import make_corpus
from talkmesh.errors import TalkmeshError
from talkmesh.evaluation.benchmark import (
    file_digest,
    load_benchmark,
    method_stages,
    predictions_done,
    run_benchmark,
)

CODETALKER = """\
model:
  preset: small
  vq: {hidden: 32, layers: 1, heads: 2, ff: 64, components: 4, code_dim: 8, codebook_size: 16,
       loss: mse}
  stage2: {d_model: 32, heads: 2, ff: 64, layers: 1, speech: {kind: mel, dim: 16}}
data: {kind: synth, root: not/the/benchmark/corpus, batch_size: 2, max_seconds: 1.0}
stages:
  motion:
    task: codetalker-stage1
    train: {lr: 1.0e-3, epochs: 1, accelerator: cpu, out_dir: runs/tiny_ct/motion}
  speech:
    task: codetalker-stage2
    init: runs/tiny_ct/motion/model.safetensors
    train: {lr: 1.0e-3, epochs: 3, accelerator: cpu, out_dir: runs/tiny_ct/speech}
"""
VOCA = """\
task: voca
model:
  preset: small
  speech: {kind: mel, dim: 16}
  conv_channels: [8, 8]
  hidden: 16
  latent: 4
data: {kind: synth, root: not/the/benchmark/corpus, batch_size: 2, max_seconds: 1.0}
train: {lr: 1.0e-3, epochs: 1, accelerator: cpu, out_dir: runs/tiny_voca}
"""


def benchmark_yaml(root: Path, **changes: str | None) -> str:
    lines = {
        "name": "tiny",
        "data": f"{{kind: synth, root: {root / 'corpus'}, split: test}}",
        "seeds": "[0, 1]",
        "work_dir": str(root / "work"),
        "docs_dir": str(root / "docs"),
        "baselines": "[static, procedural]",
        "methods": (
            f"\n  codetalker: {{recipe: {root / 'ct.yaml'}, overrides: [data.batch_size=3],"
            " stage_overrides: {speech: [train.epochs=1]}}"
            f"\n  voca: {{recipe: {root / 'voca.yaml'}}}"
        ),
        "ablation": "{method: codetalker, stage: motion, seed: 0, "
        "grid: {model.vq.temporal_unit: [1, 2], model.vq.components: [4]}}",
        "speed": "{seconds: [1], repeats: 2}",
        "samples": "2",
        "video": "true",
        "video_size": "64",
        "keep_checkpoints": "true",
    }
    lines.update(changes)
    return "".join(f"{k}: {v}\n" for k, v in lines.items() if v is not None)


@pytest.fixture(scope="module")
def bench_root(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("bench")
    make_corpus(root / "corpus", subjects=3, sentences=3, seed=3, workers=1, progress=False)
    (root / "ct.yaml").write_text(CODETALKER)
    (root / "voca.yaml").write_text(VOCA)
    (root / "bench.yaml").write_text(benchmark_yaml(root))
    return root


def mtimes(work: Path) -> dict[str, int]:
    return {str(p.relative_to(work)): p.stat().st_mtime_ns for p in work.rglob("model.safetensors")}


def test_stages_are_repointed_per_method_and_seed(bench_root):
    cfg = load_benchmark(bench_root / "bench.yaml")
    plans = {seed: method_stages(cfg, "codetalker", seed) for seed in (0, 1)}
    work = bench_root / "work" / "codetalker"
    for seed, (motion, speech) in plans.items():
        assert motion.out_dir == work / f"seed{seed}" / "motion"
        assert speech.recipe.init == str(work / f"seed{seed}" / "motion" / "model.safetensors")
        assert motion.recipe.train.seed == speech.recipe.train.seed == seed
        assert motion.recipe.data.root == str(bench_root / "corpus")  # the benchmark's data
        assert motion.recipe.data.batch_size == 3  # overrides reach every stage
        assert speech.recipe.train.epochs == 1 and motion.recipe.train.epochs == 1
    (voca,) = method_stages(cfg, "voca", 1)
    assert (
        voca.out_dir == bench_root / "work" / "voca" / "seed1" / "voca" and voca.recipe.init is None
    )


def test_the_default_benchmark_names_real_recipes_stages_and_keys():
    from dataclasses import fields

    from talkmesh.models.codetalker.vq import VQConfig

    root = Path(__file__).resolve().parents[1]
    cfg = load_benchmark(root / "configs" / "benchmark_synth.yaml", check_data=False)
    assert set(cfg.methods) == {"codetalker", "faceformer", "voca", "meshtalk"}
    assert cfg.seeds == (0, 1, 2) and cfg.data.root == "corpus/synth"
    vq = {f.name for f in fields(VQConfig)}
    assert {k.removeprefix("model.vq.") for k in cfg.ablation.grid} <= vq
    for method in cfg.methods:
        plans = method_stages(cfg, method, 2)
        assert all(p.out_dir.parts[-3:-1] == (method, "seed2") for p in plans)
        for earlier, later in zip(plans, plans[1:]):  # multi-stage: init is the new release
            assert later.recipe.init == str(earlier.release)


def test_claims_compare_means_against_seed_spread_and_count_seed_pairs():
    from talkmesh.evaluation.benchmark import aggregate, check_claims

    def seeds(lves):
        return [{"physical": {"lve": v, "fdd": -v, "mve": v, "lip_sync": 0.5}} for v in lves]

    per_seed = {
        "codetalker": seeds([1.0, 1.1, 1.2]),
        "faceformer": seeds([2.0, 1.15, 1.3]),
        "meshtalk": seeds([5.0, 5.1, 5.2]),
    }
    agg = {m: aggregate(dict(enumerate(r))) for m, r in per_seed.items()}
    claims = {(c["metric"], c["better"], c["worse"]): c for c in check_claims(agg, per_seed)}
    lve = claims[("lve", "codetalker", "faceformer")]
    assert lve["verdict"] == "within seed variance"  # 0.38 apart, stds 0.1 + 0.46
    assert (lve["seed_pairs_holding"], lve["seed_pairs"]) == (8, 9)  # 1.2 > 1.15 once
    assert claims[("lve", "faceformer", "meshtalk")]["verdict"] == "holds"
    fdd = claims[("fdd", "codetalker", "meshtalk")]  # |FDD|: 1.0-1.2 against 5.0-5.2
    assert fdd["verdict"] == "holds" and fdd["seed_pairs_holding"] == 9


@pytest.mark.parametrize(
    "changes, message",
    [
        ({"methods": "\n  voca: {recipe: nowhere.yaml}"}, "recipe not found: nowhere.yaml"),
        ({"methods": "\n  voca: {recipee: x.yaml}"}, "unknown config key methods.voca.recipee"),
        ({"colour": "red"}, "unknown config key colour"),
        ({"methods": "\n  voca: {recipe: EMPTY}"}, "neither task: (one stage) nor stages:"),
        (
            {"methods": "\n  ct: {recipe: CT, stage_overrides: {audio: [train.lr=1]}}"},
            "has no stage 'audio'",
        ),
        (
            {"methods": "\n  ct: {recipe: CT, overrides: [train.lrate=1]}"},
            "unknown config key train.lrate",
        ),
        ({"data": "{kind: synth, root: /no/corpus}"}, "dataset directory not found: /no/corpus"),
        ({"baselines": "[static, mean]"}, "unknown baseline 'mean'"),
        ({"seeds": "[]"}, "seeds must be a non-empty list"),
        ({"ablation": "{method: nope, grid: {model.vq.components: [4]}}"}, "'nope' is not in"),
        (
            {"ablation": "{method: voca, stage: voca, grid: {model.latent: [4]}}"},
            "reconstructs through a CodeTalker stage-1",
        ),
    ],
)
def test_config_errors_are_one_line(bench_root, tmp_path, capsys, changes, message):
    (tmp_path / "empty.yaml").write_text("data: {kind: synth}\n")
    subs = {"EMPTY": str(tmp_path / "empty.yaml"), "CT": str(bench_root / "ct.yaml")}
    for key, value in subs.items():
        changes = {k: v.replace(key, value) for k, v in changes.items()}
    if "methods" in changes:
        changes.setdefault("ablation", None)  # it names the default methods
    path = tmp_path / "bad.yaml"
    work = {"work_dir": str(tmp_path / "work"), "docs_dir": str(tmp_path / "docs")}
    path.write_text(benchmark_yaml(bench_root, **{**work, **changes}))
    with pytest.raises(TalkmeshError, match="^" + str(path)) as err:
        load_benchmark(path)
    assert message in str(err.value) and "\n" not in str(err.value)
    assert main(["benchmark", str(path), "--dry-run"]) == 2
    stderr = capsys.readouterr().err.strip()
    assert stderr.startswith("talkmesh: error: ") and "\n" not in stderr and message in stderr
    assert not (tmp_path / "work").exists()


def test_dry_run_prints_every_step_and_runs_nothing(bench_root, capsys):
    assert main(["benchmark", str(bench_root / "bench.yaml"), "--dry-run", "--only", "voca"]) == 0
    out = capsys.readouterr().out
    assert "train    voca seed 1 voca" in out and str(bench_root / "work" / "voca" / "seed1") in out
    assert "predict  voca seed 0" in out and "codetalker seed" not in out
    assert "baseline static" in out and "report" in out
    assert (
        main(["benchmark", str(bench_root / "bench.yaml"), "--dry-run", "--only", "faceformer"])
        == 2
    )
    assert "--only faceformer" in capsys.readouterr().err


def test_end_to_end_then_resume_then_partial(bench_root):
    config = bench_root / "bench.yaml"
    work, docs = bench_root / "work", bench_root / "docs"
    first = run_benchmark(config, quiet=True)

    report = json.loads(first.json.read_text())
    md = first.markdown.read_text()
    assert md.splitlines()[2:5] == ["```", f"talkmesh benchmark {config}", "```"]
    assert len(first.trained) == 2 * 3 + 2  # (2 codetalker stages + voca) x 2 seeds + 2 cells
    for method in ("codetalker", "voca"):
        seeds = report["methods"][method]["seeds"]
        assert sorted(seeds) == ["0", "1"]
        for protocol in ("codetalker", "physical"):
            lve = [seeds[s]["scores"][protocol]["lve"] for s in ("0", "1")]
            agg = report["methods"][method]["aggregate"][protocol]["lve"]
            assert all(np.isfinite(lve)) and agg["n"] == 2
            assert agg["mean"] == pytest.approx(np.mean(lve))
            assert agg["std"] == pytest.approx(np.std(lve, ddof=1))  # over the two seeds
        assert f"| {method} | " in md
        timing = seeds["1"]["training"][-1]
        assert timing["seconds"] > 0 and timing["frames_per_second"] > 0
        assert timing["batch_size"] == (3 if method == "codetalker" else 2)
    ct_lve = [
        report["methods"]["codetalker"]["seeds"][s]["scores"]["physical"]["lve"] for s in ("0", "1")
    ]
    assert ct_lve[0] != ct_lve[1]  # the seeds trained different models
    assert set(report["baselines"]) == {"static", "procedural"}
    verdicts = [c for c in report["claims"] if c["better"] == "codetalker"]
    assert {c["worse"] for c in verdicts} == {"voca"} and len(verdicts) == 2  # FDD, 2 protocols
    assert verdicts[0]["verdict"] in ("holds", "contradicted", "within seed variance")
    assert verdicts[0]["verdict"] in md
    for c in verdicts:  # every (codetalker seed, voca seed) pair, ordered as claimed or not
        ct, vo = (
            [
                abs(report["methods"][m]["seeds"][s]["scores"][c["protocol"]]["fdd"])
                for s in ("0", "1")
            ]
            for m in ("codetalker", "voca")
        )
        assert c["seed_pairs"] == 4
        assert c["seed_pairs_holding"] == sum(a < b for a in ct for b in vo)
        assert f"| {c['seed_pairs_holding']} / 4 | **{c['verdict']}** |" in md
    cells = report["ablation"]["cells"]
    assert [c["label"] for c in cells] == ["P=1, H=4", "P=2, H=4"]
    assert all(0 < c["usage"]["codes_used"] <= 16 and c["physical"]["lve"] > 0 for c in cells)
    assert [r["audio_seconds"] for r in report["speed"]["methods"]["voca"]] == [1]
    assert report["machine"]["torch_threads"] >= 1 and report["machine"]["cpu_count"] >= 1
    figures = docs / "tiny"
    for name in ("lip_distance.png", "motion_stats.png", "ablation.png"):
        assert 0 < (figures / name).stat().st_size < 200_000
        assert f"tiny/{name}" in md
    assert 0 < (figures / "tiny_side_by_side.mp4").stat().st_size < 2_000_000

    # run again: everything is done, nothing trains or predicts
    before = mtimes(work)
    timing = (work / "voca" / "seed0" / "voca" / "timing.json").read_text()
    again = run_benchmark(config, quiet=True, skip_video=True)
    assert again.trained == [] and again.predicted == []
    assert mtimes(work) == before
    assert (work / "voca" / "seed0" / "voca" / "timing.json").read_text() == timing
    assert json.loads(again.json.read_text())["command"].endswith("--skip-video")

    # a partial state: voca seed 1 killed after its last checkpoint (resumed), CodeTalker seed 1
    # stage 2 gone with its checkpoints (retrained); nothing else moves
    speech = work / "codetalker" / "seed1" / "speech"
    releases = {
        work / "voca" / "seed1": work / "voca" / "seed1" / "voca" / "model.safetensors",
        work / "codetalker" / "seed1": speech / "model.safetensors",
    }
    old_digests = {d: file_digest(r) for d, r in releases.items()}
    for release in releases.values():
        release.unlink()
    for ckpt in speech.glob("*.ckpt"):
        ckpt.unlink()
    third = run_benchmark(config, quiet=True, skip_video=True, skip_ablation=True)
    assert sorted(third.trained) == sorted([work / "voca" / "seed1" / "voca", speech])
    # predictions are redone exactly where the rebuilt release differs (training with the same
    # seed may rebuild a byte-identical one, whose predictions still hold)
    redone = [d / "pred" for d, r in releases.items() if file_digest(r) != old_digests[d]]
    assert sorted(third.predicted) == sorted(redone)
    for d in releases:
        assert predictions_done(d / "pred", releases[d])
    after = mtimes(work)
    changed = {k for k in before if after[k] != before[k]}
    assert changed == {
        "voca/seed1/voca/model.safetensors",
        "codetalker/seed1/speech/model.safetensors",
    }
    resumed = json.loads((work / "voca" / "seed1" / "voca" / "timing.json").read_text())
    assert resumed["resumed"] is True and resumed["epochs_trained"] == 0
    assert json.loads((speech / "timing.json").read_text())["resumed"] is False

    # a changed recipe (here the learning rate) makes its stages stale: retrained, with --only
    methods = f"\n  voca: {{recipe: {bench_root / 'voca.yaml'}, overrides: [train.lr=2e-3]}}"
    changed_cfg = bench_root / "changed.yaml"
    changed_cfg.write_text(benchmark_yaml(bench_root, methods=methods, ablation=None))
    fourth = run_benchmark(changed_cfg, quiet=True, skip_video=True, only=["voca"])
    assert sorted(fourth.trained) == [work / "voca" / f"seed{s}" / "voca" for s in (0, 1)]
    assert (
        mtimes(work)["codetalker/seed0/speech/model.safetensors"]
        == after["codetalker/seed0/speech/model.safetensors"]
    )
    assert "codetalker" not in json.loads(fourth.json.read_text())["methods"]


def test_report_renders_one_seed_no_claims_and_a_discussion_link():
    from talkmesh.evaluation.benchmark import aggregate, render_markdown

    scores = {
        p: {"lve": 5e-3, "fdd": 4e-4, "mve": 1e-3, "lip_sync": 0.5}
        for p in ("codetalker", "physical")
    }
    timing = {
        "stage": "voca",
        "task": "voca",
        "epochs": 3,
        "batch_size": 2,
        "max_seconds": 1.0,
        "seconds": 75.0,
        "frames_per_second": 40.0,
        "resumed": True,
    }
    seed = {"scores": scores, "training": [timing], "predict": {"seconds": 4.2}}
    report = {
        "name": "one",
        "command": "talkmesh benchmark one.yaml",
        "finished": "now",
        "talkmesh": "0",
        "config": {"work_dir": "runs/one"},
        "seeds": [0],
        "machine": {
            "cpu_model": "cpu",
            "usable_cpus": 1,
            "cpu_count": 2,
            "torch": "2",
            "torch_threads": 1,
            "python": "3",
            "platform": "os",
            "load_average": None,
        },
        "data": {
            "kind": "synth",
            "root": "c",
            "split": "test",
            "sequences": 2,
            "frames": 9,
            "motion_fps": 30.0,
        },
        "methods": {"voca": {"seeds": {"0": seed}, "aggregate": aggregate({0: scores})}},
        "baselines": {
            "static": {"scores": {p: {**s, "lip_sync": None} for p, s in scores.items()}}
        },
        "claims": [],
        "discussion": "docs/why.md#voca",
        "ablation": None,
        "speed": None,
        "samples": ["a"],
        "figures": {"notes": ["no video: the dataset has no faces (.ply) to render"]},
    }
    lines = render_markdown(report).splitlines()
    assert "| voca | 50.000 | 40.000 | 1.000 | 0.500 | 50.000 |" in lines  # anchor units, one seed
    assert "| voca | 5.000 | 0.400 | 1.000 | 0.500 | 5.000 |" in lines  # physical: mm
    assert "| static (baseline) | 5.000 | 0.400 | 1.000 | - | - |" in lines  # no lip sync
    assert "No claim applies: the config lacks the pairs of methods they compare." in lines
    assert (
        "Why these orderings come out as they do (written by hand, not by this command): "
        "[docs/why.md](docs/why.md#voca)." in lines
    )
    assert "- no video: the dataset has no faces (.ply) to render" in lines
    assert not any(line.startswith(("## Ablation", "## Speed", "![")) for line in lines)
    assert "| voca | voca | voca | 3 | 2 | 1.0 | 1m15s (resumed) | 40 | 4s |" in lines


def test_a_checkpoint_that_would_run_code_is_refused_before_resuming(bench_root, tmp_path):
    import torch

    from talkmesh.evaluation.benchmark.steps import train_stage

    marker = tmp_path / "pwned"

    class Payload:
        def __reduce__(self):  # unpickling calls open(marker, "w"): a file appears if it runs
            return (open, (str(marker), "w"))

    work = {"work_dir": str(tmp_path / "work"), "docs_dir": str(tmp_path / "docs")}
    (tmp_path / "b.yaml").write_text(benchmark_yaml(bench_root, ablation=None, **work))
    (plan,) = method_stages(load_benchmark(tmp_path / "b.yaml"), "voca", 0)
    plan.out_dir.mkdir(parents=True)
    torch.save({"epoch": 3, "state_dict": {}, "payload": Payload()}, plan.out_dir / "last.ckpt")
    with pytest.raises(TalkmeshError, match="last.ckpt: refused") as err:
        train_stage(plan, keep_checkpoints=True, progress=False)
    assert "\n" not in str(err.value) and "delete it" in str(err.value)
    assert not marker.exists()
    assert not plan.release.exists() and not (plan.out_dir / "timing.json").exists()
