"""LIBERO-Gen's task layer: the Combination suite is the authors' task set, with the appendix's counts."""

import re
from collections import Counter
from pathlib import Path

from bpp.envs.libero.suites import BOWL, combination, instruction_counts

# The appendix's held-out tasks (pick, place key) with its counts: training tasks with the same pick and a
# different place, and with a different pick and the same place.
APPENDIX = {
    ("TC", "CB"): (9, 8),
    ("TD", "PL"): (7, 9),
    ("NB", "bowl_1"): (9, 4),
    ("NP", "ST"): (9, 9),
    ("CB", "bowl_2"): (9, 8),
    ("CB", "WC"): (9, 8),
    ("PL", "bowl_1"): (9, 4),
    ("PL", "TC"): (9, 7),
    ("ST", "RK"): (9, 9),
    ("WC", "BPR"): (8, 9),
}


def test_combination_has_the_papers_size_and_held_out_tasks():
    suite = combination()
    assert len(suite.train) == 164 and len(suite.test) == 10  # "10 original + 164 generated" = 174
    assert [(t.pick, t.place_key) for t in suite.test] == list(APPENDIX)
    assert suite.test[0].instruction == "pick up the black bowl from table center and place it on the cookie box"
    held = {(t.pick, t.place_key) for t in suite.test}
    assert not [t for t in suite.train if (t.pick, t.place_key) in held]  # never seen jointly in training
    assert len({t.code for t in (*suite.train, *suite.test)}) == 174


def test_combination_reproduces_every_count_in_the_appendix():
    suite = combination()
    assert {(t.pick, t.place_key): suite.similar(t) for t in suite.test} == APPENDIX


def test_combination_training_tasks_are_the_authors_published_list():
    lines = (Path(__file__).parent / "data" / "liberogen_combination_training_tasks.txt").read_text().splitlines()
    published = Counter((pick, re.sub(r" \d$", "", place)) for pick, place in (line.split("|") for line in lines))
    assert instruction_counts(combination().train) == published


def test_every_task_is_one_of_nine_options_and_never_where_a_bowl_is():
    for task in (*combination().train, *combination().test):
        assert task.place not in (task.pick, task.other)
        assert task.place == BOWL or task.place_phrase.startswith(("on ", "next ", "between "))
