"""LIBERO-Gen Chain's language: every instruction of the suite as steps the demonstrator can run and goals LIBERO's
predicates check (LIBERO-Goal's scene: a bowl, a plate, a cream cheese box, a wine bottle, a cabinet with drawers,
a stove and a wine rack).

An instruction is one step ("put the bowl on the plate") or two ("open the top drawer and then put the bowl on
the plate", "open the middle drawer of the cabinet and put the cream cheese inside"). A second-step task's label
may end in a repeat number ("put the bowl on the stove 3"), which names no state (docs/liberogen/chain-analysis.md)
and is dropped here. How the phrases map to BDDL follows LIBERO-Goal's own goals (the same document).

The suite itself (which tasks, their initial states and splits) is not built yet; this is its vocabulary.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

OBJECTS = {
    "bowl": "akita_black_bowl_1",
    "cream cheese": "cream_cheese_1",
    "wine bottle": "wine_bottle_1",
    "plate": "plate_1",
}
"""Movable objects by the name instructions give them."""
PLACES = {
    "in front of the stove": "main_table_stove_front_region",
    "on the stove": "flat_stove_1_cook_region",
    "on top of the cabinet": "wooden_cabinet_1_top_side",
    "on the rack": "wine_rack_1_top_region",
    "on the plate": "plate_1",
    "in the bowl": "akita_black_bowl_1",
    "on the cream cheese": "cream_cheese_1",
    "on the bowl region": "main_table_akita_black_bowl_region",
    "on the cream cheese region": "main_table_cream_cheese_region",
    "on the wine bottle region": "main_table_wine_bottle_region",
}
"""Where "put the X <place>" puts it: an object or a region (LIBERO's ``On``). Drawers are ``In``: see
:data:`DRAWERS`."""
DRAWERS = {"top drawer": "top", "middle drawer of the cabinet": "middle"}
"""The drawers by the name instructions give them (the demonstrator's names)."""
DRAWER_REGIONS = {"top": "wooden_cabinet_1_top_region", "middle": "wooden_cabinet_1_middle_region"}
"""The drawers as LIBERO's regions."""


@dataclass(frozen=True)
class Step:
    """One step: ``operator`` (a key of :data:`bpp.envs.libero.demonstrator.OPERATORS`) with its ``arguments``,
    and the BDDL predicate that holds once it is done (``goal``)."""

    operator: str
    arguments: tuple[tuple[str, str], ...]
    goal: str

    @property
    def kwargs(self) -> dict[str, str]:
        return dict(self.arguments)


def _put(obj: str, place: str, opened: str | None) -> Step:
    name = OBJECTS[obj]
    if place in ("inside", "in the top drawer"):  # "inside": the drawer the first step opened
        region = DRAWER_REGIONS["top"] if place == "in the top drawer" else opened
        if region is None:
            raise ValueError(f"'put the {obj} inside' needs a first step that opens a drawer")
        return Step("place", (("obj", name), ("target", region)), f"(In {name} {region})")
    if place not in PLACES:
        raise ValueError(f"unknown place {place!r} in 'put the {obj} {place}'; known: {', '.join(PLACES)}")
    return Step("place", (("obj", name), ("target", PLACES[place])), f"(On {name} {PLACES[place]})")


_PUT = re.compile(r"put the (bowl|cream cheese|wine bottle) (.+)")
_OPEN = re.compile(r"open the (top drawer|middle drawer of the cabinet)")


def parse_step(text: str, opened: str | None = None) -> Step:
    """One step's words -> :class:`Step`; `opened` is the drawer a previous step opened (for "... inside")."""
    text = text.strip()
    if text == "turn on the stove":
        return Step("turn_on", (), "(Turnon flat_stove_1)")
    if text == "push the plate to the front of the stove":
        return Step("push", (), f"(On plate_1 {PLACES['in front of the stove']})")
    if match := _OPEN.fullmatch(text):
        drawer = DRAWERS[match.group(1)]
        return Step("open", (("drawer", drawer),), f"(Open {DRAWER_REGIONS[drawer]})")
    if match := _PUT.fullmatch(text):
        return _put(match.group(1), match.group(2), opened)
    raise ValueError(f"not a LIBERO-Gen Chain step: {text!r}")


def parse_instruction(text: str) -> list[Step]:
    """A Chain task's label -> its one or two steps, in order (a trailing repeat number is dropped)."""
    text = re.sub(r" \d+$", "", text.strip())
    parts = re.split(r" and (?:then )?(?=put |open |push |turn )", text, maxsplit=1)
    steps = [parse_step(parts[0])]
    if len(parts) == 2:
        drawer = steps[0].kwargs.get("drawer")
        steps.append(parse_step(parts[1], None if drawer is None else DRAWER_REGIONS[drawer]))
    return steps


def goal_problem(instruction: str, base_text: str) -> str:
    """A LIBERO-Goal problem (`base_text`, any of the ten: they share one scene and initial state) with
    `instruction` as its language and the conjunction of its steps' goals as its goal. BDDL has no order: the
    steps' order is the instruction's."""
    from bpp.envs.libero.bddl import dumps, parse, set_section

    problem = parse(base_text)
    goals = [step.goal.strip("()").split() for step in parse_instruction(instruction)]
    set_section(problem, ":language", re.sub(r" \d+$", "", instruction).split())
    set_section(problem, ":goal", [["And", *goals]])
    return dumps(problem)
