"""What a benchmark result comes from, said plainly: data, model variants, training budgets.

:func:`scope_lines` is the "What these numbers are" section of a benchmark page
(``talkmesh benchmark``): which data the methods saw, which recipe (variant) each one trained and
how much of that recipe's own training it got, so that no reader takes a result on a small
synthetic run for a statement about the papers' configurations on recorded faces.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

RECORDED = ("vocaset", "biwi")  # recorded faces, the data the papers measured on


def _epochs(overrides: list[str]) -> int | None:
    for o in reversed(overrides):
        key, _, value = o.partition("=")
        if key.strip() == "train.epochs":
            try:
                return int(value)
            except ValueError:
                return None
    return None


def method_budgets(spec: dict[str, Any]) -> list[tuple[str, int | None, int | None]]:
    """(stage, epochs trained, the recipe's own epochs) of one benchmark method."""
    from talkmesh.errors import TalkmeshError
    from talkmesh.training.trainer import load_recipes

    try:
        stages = load_recipes(Path(spec["recipe"]))
    except (TalkmeshError, OSError):
        return []
    out = []
    common = list(spec.get("overrides", []))
    for name, recipe in stages:
        stage = common + list(spec.get("stage_overrides", {}).get(name, []))
        trained = _epochs(stage)
        out.append((name, recipe.train.epochs if trained is None else trained, recipe.train.epochs))
    return out


def scope_lines(report: dict[str, Any]) -> list[str]:
    """Markdown lines: the data, the variant and the budget behind every result of ``report``."""
    data = report["data"]
    kind = data["kind"]
    out = ["", "## What these numbers are", ""]
    if kind in RECORDED:
        out.append(
            f"Data: `{kind}`, recorded faces, the kind of data the papers report on; the split "
            f"and protocol above say which of their numbers these compare with."
        )
    else:
        out.append(
            f"Data: `{kind}`, not the recorded faces (VOCASET, BIWI) the papers measured on. "
            + (
                "The synthetic corpus's lips are a deterministic function of the phones and the "
                "speaker's style, so these results say how the methods compare on that corpus "
                "only, not how they rank on real capture."
                if kind == "synth"
                else "Results say how the methods compare on this data only."
            )
        )
    out += [
        "",
        "Variants and budgets: each method is the recipe named below (not the papers' "
        "configurations unless the recipe says so; docs/guide/recipes.md lists those), trained for the "
        "epochs shown out of the recipe's own.",
        "",
        "| method | recipe | stage: epochs trained / recipe's epochs |",
        "|---|---|---|",
    ]
    methods = report.get("config", {}).get("methods", {})
    for name, spec in methods.items():
        budgets = method_budgets(spec)
        cells = ", ".join(
            f"{stage}: {got} / {full}" + (f" ({100 * got / full:.0f}%)" if full else "")
            for stage, got, full in budgets
        )
        out.append(f"| {name} | `{spec['recipe']}` | {cells or 'recipe not readable here'} |")
    out += [
        "",
        "A claim below that *holds* or is *contradicted* does so for these variants, this data and "
        "these budgets; it does not confirm or refute the papers.",
    ]
    return out
