"""The recipes under configs/ against the official configs (configs/official_hparams.json) and
the docs table (docs/guide/recipes.md) rendered from that file."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from talkmesh.config import to_dict
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
    from talkmesh.models.meshtalk import MeshTalkConfig, meshtalk_config
    from talkmesh.models.meshtalk_prior import PriorConfig, prior_config
    from talkmesh.training.meshtalk import _config

    if task == "meshtalk":
        cfg = _config(MeshTalkConfig, meshtalk_config, model, info.num_vertices, info.motion_fps)
    else:
        cfg = _config(PriorConfig, prior_config, model, info.motion_fps)
    return to_dict(cfg)


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
    from talkmesh.models.meshtalk import MeshTalkModel
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
