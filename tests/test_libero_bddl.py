"""BDDL as data: parse / write round trip, and Combination tasks written from their scene's problem."""

import pytest

from bpp.benchmarks.libero.bddl import BDDLError, dumps, objects, parse, section
from bpp.benchmarks.libero.suites import combination, combination_problem

# A small problem in LIBERO-Spatial's layout, written for this test (not one of LIBERO's files).
SCENE = """
(define (problem Test_Scene)  ; a comment
  (:domain robosuite)
  (:language Pick the akita black bowl next to the plate and place it on the plate)
  (:regions
    (next_to_plate_region (:target main_table) (:ranges ((0.0 0.3 0.02 0.32))))
    (table_center (:target main_table) (:ranges ((-0.1 -0.01 -0.05 0.01))))
    (top_side (:target wooden_cabinet_1))
  )
  (:fixtures main_table - table wooden_cabinet_1 - wooden_cabinet flat_stove_1 - flat_stove)
  (:objects akita_black_bowl_1 akita_black_bowl_2 - akita_black_bowl cookies_1 - cookies plate_1 - plate)
  (:obj_of_interest akita_black_bowl_1 plate_1)
  (:init
    (On akita_black_bowl_1 main_table_table_center)
    (On akita_black_bowl_2 main_table_next_to_plate_region)
    (On plate_1 main_table_plate_region)
    (On wooden_cabinet_1 main_table_cabinet_region)
  )
  (:goal (And (On akita_black_bowl_1 plate_1)))
)
"""


def test_parse_and_write_round_trip():
    problem = parse(SCENE)
    assert parse(dumps(problem)) == problem
    assert section(problem, ":goal") == [":goal", ["And", ["On", "akita_black_bowl_1", "plate_1"]]]
    fixtures = ["main_table", "wooden_cabinet_1", "flat_stove_1"]
    assert objects(problem) == [*fixtures, "akita_black_bowl_1", "akita_black_bowl_2", "cookies_1", "plate_1"]


@pytest.mark.parametrize(
    ("text", "message"), [("(define (problem x)", "unclosed"), ("(a))", "unbalanced"), ("(a) (b)", "expected one")]
)
def test_malformed_bddl_is_refused_saying_where(text, message):
    with pytest.raises(BDDLError, match=message):
        parse(text)


def test_combination_tasks_are_written_from_their_scene():
    suite = combination()
    on_plate = next(t for t in suite.train if t.scene.name == "N1" and t.bowl == 1 and t.place == "bowl")
    problem = parse(combination_problem(on_plate, SCENE))
    init = section(problem, ":init")[1:]
    assert init[:2] == [
        ["On", "akita_black_bowl_1", "main_table_table_center"],
        ["On", "akita_black_bowl_2", "plate_1"],
    ]
    assert ["On", "plate_1", "main_table_plate_region"] in init and len(init) == 4  # the rest as LIBERO has it
    assert section(problem, ":goal") == [":goal", ["And", ["On", "akita_black_bowl_1", "akita_black_bowl_2"]]]
    assert section(problem, ":obj_of_interest")[1:] == ["akita_black_bowl_1", "akita_black_bowl_2"]
    assert " ".join(section(problem, ":language")[1:]) == (
        "Pick up the black bowl from table center and place it in the black bowl on the plate"
    )
    to_region = next(t for t in suite.train if t.place == "NR")  # a table region, not an object
    problem = parse(combination_problem(to_region, SCENE))
    picked = f"akita_black_bowl_{to_region.bowl}"
    assert section(problem, ":goal")[1] == ["And", ["On", picked, "main_table_next_to_ramekin_region"]]
    assert section(problem, ":obj_of_interest")[1:] == [picked]
