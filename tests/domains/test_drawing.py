"""The ``drawing`` every environment's layout carries for the page: every terrain, machine and
gravity colour the environment has, with its name for people and its colour; a study's own
kinds in the study's colours (else a spare one), the built-in kinds in the page's own."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from server import domains
from server.domains.base import Environment
from server.domains.drawing import COLOURS, SPARE_COLOURS
from server.domains.spec import EnvironmentSpec

REPOSITORY = Path(__file__).resolve().parents[2]
HEX = re.compile(r"^#[0-9A-Fa-f]{6}$")

VINEYARD = """task: Vines = rows 1-2, columns 1-2
task: Soil = rows 1-2, columns 4-5
start: rows 3-4
    0123456
  0 .......
  1 .vv.ss.
  2 .vv.ss.
  3 .......
  4 T.P.Q..
"""
# Starts in row 0 short of the last column: none trapped (gravity south in row 2 would be).
GRAVITY = """task: A
start: rows 0, columns 1-3
gravity of orange: north
gravity of yellow: west
    01234
  0 A....
  1 .o.y.
  2 .....
"""


def kinds(env: Environment) -> dict[str, dict[str, dict[str, object]]]:
    return {
        category: {kind["name"]: kind for kind in listed}
        for category, listed in env.describe()["drawing"].items()
    }


@pytest.mark.parametrize("name", domains.NAMES)
def test_every_kind_a_built_in_environment_draws_is_described(name: str) -> None:
    env = domains.make(name)
    drawn = kinds(env)
    terrains = {terrain for row in env.layout["terrain"] for terrain in row}
    if env.layout["walls"]:
        terrains.add("wall")
    assert terrains <= set(drawn["terrains"])
    assert {m["machine"] for m in env.layout["machines"]} <= set(drawn["machines"])
    assert {c["colour"] for c in env.layout["colours"]} <= set(drawn["colours"])
    for category in drawn.values():
        for kind in category.values():
            assert kind["built_in"] is True
            assert kind["colour"] == COLOURS[str(kind["name"])]
            assert kind["label"] == str(kind["name"]).capitalize()


def test_the_built_in_colours_are_the_page_s() -> None:
    script = (REPOSITORY / "server/static/js/grid.js").read_text()
    for name in ("floor", "dirt", "soil", "grass", "crops", "orange", "green", "purple"):
        match = re.search(rf'{name}: \{{ fill: "(#[0-9a-fA-F]{{6}})"', script)
        assert match is not None and match.group(1) == COLOURS[name], name


def test_a_study_s_own_terrain_and_machines_have_the_study_s_colours_and_names() -> None:
    env = EnvironmentSpec(
        name="custom",
        domain="farming",
        map=VINEYARD,
        terrains={"v": "vines"},
        machines={"T": "trellis", "Q": "quad bike"},
        works_on={"trellis": "vines", "quad bike": "soil"},
        # A colour for a built-in name does not change how the page draws it.
        colours={"vines": "#6b8e23", "trellis": "#8b4513", "soil": "#000000"},
    ).build()
    drawn = kinds(env)
    assert drawn["terrains"]["vines"] == {
        "name": "vines",
        "label": "Vines",
        "colour": "#6b8e23",
        "built_in": False,
        "machines": ["trellis"],
    }
    assert drawn["terrains"]["soil"]["colour"] == COLOURS["soil"]
    assert drawn["terrains"]["soil"]["machines"] == ["plow", "quad bike"]
    assert drawn["terrains"]["dirt"]["machines"] == []
    assert drawn["machines"]["trellis"] == {
        "name": "trellis",
        "label": "Trellis",
        "colour": "#8b4513",
        "built_in": False,
        "terrain": "vines",
    }
    # No colour given: a spare one; the name for people keeps its words.
    assert drawn["machines"]["quad bike"]["colour"] == SPARE_COLOURS[0]
    assert drawn["machines"]["quad bike"]["label"] == "Quad bike"
    assert list(drawn["machines"]) == ["plow", "sprinkler", "harvester", "trellis", "quad bike"]


def test_a_study_s_own_gravity_colour_has_the_study_s_colour() -> None:
    env = EnvironmentSpec(
        name="custom",
        domain="gravity",
        map=GRAVITY,
        gravity_colours={"y": "yellow"},
        colours={"yellow": "#F0E442"},
    ).build()
    drawn = kinds(env)
    assert drawn["colours"]["yellow"]["colour"] == "#F0E442"
    assert drawn["colours"]["yellow"]["built_in"] is False
    assert drawn["colours"]["orange"]["colour"] == COLOURS["orange"]
    for category in drawn.values():
        assert all(HEX.match(str(kind["colour"])) for kind in category.values())
