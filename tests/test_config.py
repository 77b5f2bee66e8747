from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import pytest

from talkmesh.config import apply_overrides, from_dict, load_config, to_dict
from talkmesh.errors import TalkmeshError


@dataclass(frozen=True)
class Inner:
    width: int = 8
    rate: float = 0.5
    kind: Literal["a", "b"] = "a"
    sizes: tuple[int, ...] = (1, 2)

    def __post_init__(self) -> None:
        if self.width < 1:
            raise ValueError("inner.width must be at least 1")


@dataclass(frozen=True)
class Outer:
    name: str
    inner: Inner = Inner()
    path: str | None = None
    extra: dict[str, float] = field(default_factory=dict)


def test_yaml_recipe_maps_onto_dataclasses(tmp_path):
    path = tmp_path / "r.yaml"
    path.write_text("name: run\ninner:\n  width: 16\n  rate: 1\n  sizes: [3, 4, 5]\n")
    cfg = load_config(Outer, path)
    assert cfg == Outer("run", Inner(16, 1.0, "a", (3, 4, 5)))
    assert isinstance(cfg.inner.rate, float)


def test_round_trip_through_plain_dicts():
    cfg = Outer("x", Inner(4, 0.25, "b", (7,)), path="p", extra={"k": 2.0})
    assert from_dict(Outer, to_dict(cfg)) == cfg


def test_dotted_overrides(tmp_path):
    path = tmp_path / "r.yaml"
    path.write_text("name: run\n")
    cfg = load_config(
        Outer, path, ["inner.rate=1e-4", "inner.kind=b", "path=out/x", "inner.sizes=[9]"]
    )
    assert cfg.inner.rate == pytest.approx(1e-4)
    assert cfg.inner.kind == "b" and cfg.path == "out/x" and cfg.inner.sizes == (9,)
    data = {"a": {"b": 1}}
    assert apply_overrides(data, ["a.b=2"]) == {"a": {"b": 2}}
    assert data == {"a": {"b": 1}}  # the input is not changed


@pytest.mark.parametrize(
    "data, fragment",
    [
        ({"name": "x", "inner": {"widht": 3}}, "unknown config key inner.widht"),
        ({"name": "x", "inner": {"width": "wide"}}, "inner.width: expected an integer"),
        ({"name": "x", "inner": {"kind": "c"}}, "inner.kind: 'c' is not one of"),
        ({"name": "x", "inner": {"width": 0}}, "inner.width must be at least 1"),
        ({"inner": {}}, "name"),
        ({"name": 3}, "name: expected a string"),
    ],
)
def test_bad_configs_give_one_line_errors(data, fragment):
    with pytest.raises(TalkmeshError, match=None) as e:
        from_dict(Outer, data)
    assert fragment in str(e.value)
    assert "\n" not in str(e.value)


def test_bad_files(tmp_path):
    with pytest.raises(TalkmeshError, match="not found"):
        load_config(Outer, tmp_path / "missing.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: [unclosed\n")
    with pytest.raises(TalkmeshError, match="bad.yaml.*not valid YAML"):
        load_config(Outer, bad)
    with pytest.raises(TalkmeshError, match="key.sub=value"):
        apply_overrides({}, ["novalue"])
