"""The recipes under configs/ against the official configs (configs/official_hparams.json) and
the docs table (docs/guide/recipes.md) rendered from that file."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from talkmesh.config import from_dict, to_dict
from talkmesh.datasets.reader import BIWI, VOCASET
from talkmesh.training.trainer import DatasetInfo, load_recipes

ROOT = Path(__file__).resolve().parents[1]
TABLE = json.loads((ROOT / "configs" / "official_hparams.json").read_text())["rows"]
INFO = {
    "VOCASET": DatasetInfo(VOCASET.num_vertices, VOCASET.motion_fps, VOCASET.train_subjects),
    "BIWI": DatasetInfo(BIWI.num_vertices, BIWI.motion_fps, BIWI.train_subjects),
}


def model_config(task: str, model: dict, info: DatasetInfo) -> dict:
    """The model config a recipe's model section resolves to (presets applied)."""
    if task.startswith("codetalker"):
        from talkmesh.training.codetalker import build_config

        return to_dict(build_config(model, info))
    if task == "faceformer":
        from talkmesh.training.faceformer import build_config

        return to_dict(build_config(model, info))
    from talkmesh.models.meshtalk.model import MeshTalkConfig, SamplingConfig, meshtalk_config
    from talkmesh.models.meshtalk.prior import PriorConfig, prior_config
    from talkmesh.training.meshtalk import _config

    if task == "meshtalk":
        cfg = _config(MeshTalkConfig, meshtalk_config, model, info.num_vertices, info.motion_fps)
        return to_dict(cfg)
    model = dict(model)
    sampling = to_dict(from_dict(SamplingConfig, model.pop("sampling", {}), "model.sampling"))
    return {
        **to_dict(_config(PriorConfig, prior_config, model, info.motion_fps)),
        "sampling": sampling,
    }


def resolve(row: dict) -> object:
    stages = dict(load_recipes(ROOT / row["recipe"]))
    recipe = stages[row["stage"]]
    section, _, path = row["key"].partition(".")
    if section == "model":
        value = model_config(recipe.task, recipe.model, INFO[row["dataset"]])
    else:
        value = to_dict(getattr(recipe, section))
    for part in path.split("."):
        value = value[part]
    return value


@pytest.mark.parametrize(
    "row", TABLE, ids=[f"{r['recipe'].split('/')[-1]}:{r['stage']}:{r['key']}" for r in TABLE]
)
def test_recipe_value_is_the_tables(row):
    got = resolve(row)
    if isinstance(row["value"], float):
        assert got == pytest.approx(row["value"]), row
    else:
        assert got == row["value"], row


def test_every_difference_from_the_official_code_is_explained():
    for row in TABLE:
        assert row["paper"] and row["official"], row
        if row["note"]:
            assert row["note"].startswith("differs:"), row


def render_table(rows: list[dict]) -> str:
    head = "| model | data | parameter | paper | official code | our recipe (key = value) | note |"
    lines = [head, "|---|---|---|---|---|---|---|"]
    for r in rows:
        ours = f"`{r['recipe'].split('/')[-1]}` {r['stage']}: `{r['key']} = {r['value']}`"
        lines.append(
            f"| {r['model']} | {r['dataset']} | {r['parameter']} | {r['paper']} | "
            f"{r['official']} | {ours} | {r['note']} |"
        )
    return "\n".join(lines)


def test_docs_table_is_rendered_from_the_data():
    docs = (ROOT / "docs" / "guide" / "recipes.md").read_text()
    assert render_table(TABLE) in docs, (
        "re-render docs/guide/recipes.md from configs/official_hparams.json"
    )


def test_meshtalk_weight_decay_reaches_the_decoder_only():
    import torch

    from talkmesh.errors import TalkmeshError
    from talkmesh.models.meshtalk.model import MeshTalkModel
    from talkmesh.training.trainer import decay_groups

    net = MeshTalkModel(MeshTalkModel.tiny_config())
    params = list(net.model.parameters())
    groups = decay_groups(net, params, 0.5, ("model.decoder",))
    optimizer = torch.optim.Adam(groups, lr=0.1)
    for p in params:
        p.data.fill_(1.0)  # decay moves every non-zero parameter it applies to
        p.grad = torch.zeros_like(p)  # and nothing else moves one
    before = {n: p.detach().clone() for n, p in net.model.named_parameters()}
    optimizer.step()
    moved = {n for n, p in net.model.named_parameters() if not torch.equal(p, before[n])}
    decoder = {n for n, _ in net.model.named_parameters() if n.startswith("decoder.")}
    assert moved == decoder and decoder
    assert len(decay_groups(net, params, 0.5, ())) == 1
    with pytest.raises(TalkmeshError, match="names no parameters"):
        decay_groups(net, params, 0.5, ("model.nothing",))


# Every official-exact architecture option (docs/guide/official.md, "Official-exact options") as
# an imported release sets it: the papers' recipes must switch each one on.
MESHTALK_AUDIO = {
    "audio.windows": True,
    "audio.gain": 0.01,
    "audio.input_kernel": 5,
    "audio.dilations": [2, 4, 6, 2, 4, 6],
    "audio.lookahead_ms": 500.0,
    "audio.log_floor": 1e-10,
    "audio.mel_statistics": False,
    "audio.layer_norm": False,
}
OFFICIAL_OPTIONS = {
    "meshtalk": {
        **MESHTALK_AUDIO,
        "expression_widths": [256, 128],
        "expression_output": 128,
        "vertex_norm": "per_vertex",
        "official_decoder": True,
    },
    "meshtalk-prior": {
        **MESHTALK_AUDIO,
        "layout": "official",
        "audio_source": "expression",
        "sampling.gumbel": True,
    },
    "faceformer": {
        "postnorm": True,
        "interleaved_ppe": True,
        "frame0_motion_bias": False,
        "speech.resample": "cnn",
        "speech.normalize": True,
    },
    "codetalker": {
        "vq.instance_norm": True,
        "vq.gelu_tanh": True,
        "vq.final_norm": False,
        "vq.frame_positions": False,
        "stage2.postnorm": True,
        "stage2.interleaved_ppe": True,
        "stage2.speech.resample": "cnn",
        "stage2.speech.normalize": True,
    },
}
PAPER_RECIPES = {  # recipe -> the dataset whose sizes it resolves with
    "meshtalk_paper.yaml": "VOCASET",
    "meshtalk_released.yaml": "VOCASET",
    "faceformer_vocaset.yaml": "VOCASET",
    "faceformer_biwi.yaml": "BIWI",
    "codetalker_vocaset.yaml": "VOCASET",
    "codetalker_biwi.yaml": "BIWI",
}


def lookup(config: dict, key: str):
    for part in key.split("."):
        config = config[part]
    return config


def options_of(task: str) -> dict:
    return OFFICIAL_OPTIONS["codetalker" if task.startswith("codetalker") else task]


@pytest.mark.parametrize("name", sorted(PAPER_RECIPES))
def test_paper_recipes_switch_on_every_official_exact_option(name):
    stages = load_recipes(ROOT / "configs" / name)
    assert stages
    for stage, recipe in stages:
        config = model_config(recipe.task, recipe.model, INFO[PAPER_RECIPES[name]])
        for key, want in options_of(recipe.task).items():
            got = lookup(config, key)
            assert got == (pytest.approx(want) if isinstance(want, float) else want), (
                f"{name} {stage}: model.{key} is {got!r}, the official code's is {want!r}"
            )


OFFICIAL = ROOT / "tests" / "fixtures" / "official"
IMPORTS = {  # an imported fixture release per family: the options are the importer's
    "faceformer": ([OFFICIAL / "faceformer_vocaset.pth"], "faceformer", "vocaset"),
    "codetalker": (
        [OFFICIAL / f"codetalker_vocaset_stage{i}.pth.tar" for i in (1, 2)],
        "codetalker",
        "vocaset",
    ),
    "meshtalk": ([OFFICIAL / "meshtalk"], "meshtalk", "meshtalk"),
}
SIZES = {"expression_output"}  # the fixture is smaller than the release (16, not 128)


@pytest.mark.parametrize("family", sorted(IMPORTS))
def test_the_option_list_is_what_the_importer_switches_on(family):
    from talkmesh.models.official import import_checkpoint

    paths, kind, dataset = IMPORTS[family]
    config = to_dict(import_checkpoint(paths, kind, dataset).cfg)
    tasks = ("meshtalk", "meshtalk-prior") if family == "meshtalk" else (family,)
    docs = (ROOT / "docs" / "guide" / "official.md").read_text().split("## Official-exact")[1]
    for task in tasks:
        for key, want in options_of(task).items():
            path = key
            if family == "meshtalk":
                path = ("model." if task == "meshtalk" else "prior.") + key
                path = key if key.startswith("sampling.") else path
            got = lookup(config, path)
            if key in SIZES:
                assert got > 0, key
            else:
                assert got == (pytest.approx(want) if isinstance(want, float) else want), key
            assert f"{key.split('.')[-1]}`" in docs, f"docs/guide/official.md lacks {key}"
