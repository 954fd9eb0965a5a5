"""LIBERO-Gen Chain's language: every instruction of the suite as steps the demonstrator can run and goals LIBERO's
predicates check (LIBERO-Goal's scene: a bowl, a plate, a cream cheese box, a wine bottle, a cabinet with drawers,
a stove and a wine rack).

An instruction is one step ("put the bowl on the plate") or two ("open the top drawer and then put the bowl on
the plate", "open the middle drawer of the cabinet and put the cream cheese inside"). A second-step task's label
may end in a repeat number ("put the bowl on the stove 3"), which names no state (docs/libero-gen/chain.md)
and is dropped here. How the phrases map to BDDL follows LIBERO-Goal's own goals (the same document).

**The suite** (:func:`chain`) is the authors' published task list (``chain_tasks.txt``: 21 first steps, 146
second steps, 144 seen chains and 10 unseen chains, 321 tasks), since no rule we know selects exactly its chains.
First steps and chains start from LIBERO-Goal's initial state. A second-step task starts from the end state of a
first step, written into its BDDL's ``:init``; which one is inferred (:func:`second_step_starts`): the suffix
counts an instruction's repeats over the 19 first steps whose end states allow it, taken in alphabetical order.
That rule reproduces every instruction's count of published suffixes exactly, but the order is a guess that
agrees with 9 of the appendix's 10 "present / not present" notes. The ablation view without second steps is
:func:`chain_no_second_step`.
"""

from __future__ import annotations

import re
from collections import Counter
from dataclasses import dataclass
from functools import cache, cached_property
from pathlib import Path

from bpp.benchmarks.libero.bddl import BDDLError, dumps, parse, section, set_section

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
    """One step: ``operator`` (a key of :data:`bpp.benchmarks.libero.demonstrator.OPERATORS`) with its ``arguments``,
    the BDDL predicate that holds once it is done (``goal``), and its effect: the object it ``moves`` and where it
    leaves it (``leaves_at``), both BDDL names or None."""

    operator: str
    arguments: tuple[tuple[str, str], ...]
    goal: str
    moves: str | None = None
    leaves_at: str | None = None

    @property
    def kwargs(self) -> dict[str, str]:
        return dict(self.arguments)


@dataclass(frozen=True)
class OperatorSpec:
    """An operator of LIBERO-Goal's scene, declared: the words that ask for it (a regular expression whose named
    groups are its arguments in words, each looked up in :data:`VOCABULARY`), the arguments the demonstrator's
    operator takes (its keyword <- a group), the BDDL predicate that holds once it is done (formatted with the
    groups' BDDL names), and its effect: the object it moves and where it leaves it (a group or a BDDL name), from
    which :func:`may_follow` decides what may come after it."""

    operator: str
    words: str
    goal: str
    arguments: tuple[tuple[str, str], ...] = ()
    moves: str | None = None
    leaves_at: str | None = None


_OBJ = "(?P<obj>bowl|cream cheese|wine bottle)"
_DRAWER = "(?P<drawer>top drawer|middle drawer of the cabinet)"
SPECS = (
    OperatorSpec("turn_on", "turn on the stove", "(Turnon flat_stove_1)"),
    OperatorSpec(
        "push",
        "push the plate to the front of the stove",
        "(On plate_1 main_table_stove_front_region)",
        moves="plate_1",
        leaves_at="main_table_stove_front_region",
    ),
    OperatorSpec("open", f"open the {_DRAWER}", "(Open {region})", (("drawer", "drawer"),)),
    OperatorSpec("close", f"close the {_DRAWER}", "(Close {region})", (("drawer", "drawer"),)),
    OperatorSpec(
        "place",
        f"put the {_OBJ} (?P<into>in the top drawer|inside)",
        "(In {obj} {into})",
        (("obj", "obj"), ("target", "into")),
        "obj",
        "into",
    ),
    OperatorSpec(
        "place",
        f"put the {_OBJ} (?P<place>.+)",
        "(On {obj} {place})",
        (("obj", "obj"), ("target", "place")),
        "obj",
        "place",
    ),
)
"""Every step an instruction of the Chain suite can ask for (the first that matches is the one)."""
VOCABULARY = {
    "obj": OBJECTS,
    "place": PLACES,
    "drawer": DRAWERS,
    "into": {"in the top drawer": DRAWER_REGIONS["top"], "inside": None},  # None: the drawer a first step opened
}
"""A group's words -> the name the demonstrator and BDDL use."""
HOLDERS = ("akita_black_bowl_1", "cream_cheese_1")
"""Objects that carry what was put in or on them (LIBERO-Goal's bowl and cream cheese box)."""


def may_follow(first: Step, second: Step) -> bool:
    """What may follow what (the rule inferred from the published suite; docs/libero-gen/chain.md): a second step moves
    another object than the first step did, to a place the first step did not fill, and does not lift one of the
    :data:`HOLDERS` with something the first step put in or on it."""
    if first.moves is None:  # the stove, a drawer: nothing moved
        return True
    lifts_a_holder = first.leaves_at in HOLDERS and second.moves == first.leaves_at
    return second.moves != first.moves and second.leaves_at != first.leaves_at and not lifts_a_holder


def parse_step(text: str, opened: str | None = None) -> Step:
    """One step's words -> :class:`Step` by :data:`SPECS`; `opened` is the region of the drawer a previous step
    opened (for "put the X inside")."""
    text = text.strip()
    for spec in SPECS:
        if (match := re.fullmatch(spec.words, text)) is None:
            continue
        names = {}
        for group, words in match.groupdict().items():
            if words not in VOCABULARY[group]:
                raise ValueError(f"unknown {group} {words!r} in {text!r}; known: {', '.join(VOCABULARY[group])}")
            names[group] = VOCABULARY[group][words]
        if "into" in names and names["into"] is None:
            if opened is None:
                raise ValueError(f"{text!r} needs a first step that opens a drawer")
            names["into"] = opened
        if "drawer" in names:
            names["region"] = DRAWER_REGIONS[names["drawer"]]
        return Step(
            spec.operator,
            tuple((keyword, names[group]) for keyword, group in spec.arguments),
            spec.goal.format(**names),
            names.get(spec.moves, spec.moves),
            names.get(spec.leaves_at, spec.leaves_at),
        )
    raise ValueError(f"not a LIBERO-Gen Chain step: {text!r}")


def _split(text: str) -> list[str]:
    """An instruction's words per step."""
    return re.split(r" and (?:then )?(?=put |open |close |push |turn )", text, maxsplit=1)


def parse_instruction(text: str) -> list[Step]:
    """A Chain task's label -> its one or two steps, in order (a trailing repeat number is dropped)."""
    parts = _split(re.sub(r" \d+$", "", text.strip()))
    steps = [parse_step(parts[0])]
    if len(parts) == 2:
        drawer = steps[0].kwargs.get("drawer") if steps[0].operator == "open" else None
        steps.append(parse_step(parts[1], None if drawer is None else DRAWER_REGIONS[drawer]))
    return steps


def goal_problem(instruction: str, base_text: str) -> str:
    """A LIBERO-Goal problem (`base_text`, any of the ten: they share one scene and initial state) with
    `instruction` as its language and the conjunction of its steps' goals as its goal. BDDL has no order: the
    steps' order is the instruction's."""
    problem = parse(base_text)
    goals = [step.goal.strip("()").split() for step in parse_instruction(instruction)]
    set_section(problem, ":language", re.sub(r" \d+$", "", instruction).split())
    set_section(problem, ":goal", [["And", *goals]])
    return dumps(problem)


# ----------------------------------------------------------------------------------------------- the suite
VIEWS = {
    "first_step": "libero_goal_chain_firststep_view",
    "second_step": "libero_goal_chain_secondstep_view",
    "seen_chains": "libero_goal_chain_selected_inverse_view",
    "unseen_chains": "libero_goal_chain_selected_view",
}
"""The suite's views (our names -> the authors' split keys). The unseen chains are held out; the rest train."""
CANDIDATES = "candidate_chains"
"""The view of the chains :func:`chain_candidates` generates (not one of the authors')."""
TASK_LIST = Path(__file__).with_name("chain_tasks.txt")
"""The published task list, ``<split key>|<label>`` per line, from the authors' website manifest."""


@dataclass(frozen=True)
class ChainTask:
    """One Chain task: its published ``label``, its ``view`` (a key of :data:`VIEWS`) and, for a second-step task,
    ``start``: the first step whose end state it starts from (None: LIBERO-Goal's initial state)."""

    label: str
    view: str
    start: str | None = None

    @property
    def instruction(self) -> str:
        return re.sub(r" \d+$", "", self.label)

    @cached_property
    def steps(self) -> list[Step]:
        return parse_instruction(self.label)

    @property
    def name(self) -> str:
        """A file- and id-safe name: the label (with its repeat number) in dashes."""
        return re.sub(r"[^a-z0-9]+", "-", self.label.lower()).strip("-")

    @property
    def code(self) -> str:
        return self.label

    @property
    def libero_source(self) -> tuple[str, str]:
        """(LIBERO suite folder, problem name) of the LIBERO-Goal problem with this instruction (its original tasks)."""
        return "libero_goal", self.instruction.replace(" ", "_")

    @property
    def families(self) -> tuple[str, ...]:
        """What a generation report counts tries and successes by: the view and each step's operator + object."""
        return (f"view {self.view}", *(f"step {_step_key(s)}" for s in self.steps))

    def describe(self) -> dict:
        return {
            "instruction": self.instruction,
            "label": self.label,
            "view": self.view,
            "start": self.start,
            "steps": [{"operator": s.operator, **s.kwargs, "goal": s.goal} for s in self.steps],
        }

    def problem(self, base_text: str) -> str:
        """Its BDDL problem, from a LIBERO-Goal problem (any: they share scene and initial state): the steps' goals,
        and for a second-step task the first step's effect in ``:init``."""
        problem = parse(goal_problem(self.label, base_text))
        if self.start is None:
            return dumps(problem)
        first = parse_step(self.start)
        init = section(problem, ":init")[1:]
        if first.operator in ("turn_on", "open", "close"):
            init.append(first.goal.strip("()").split())
        else:  # an object moved: its placement is the step's goal
            moved = first.goal.strip("()").split()
            kept = [p for p in init if not (isinstance(p, list) and len(p) == 3 and p[1] == moved[1])]
            if len(kept) != len(init) - 1:
                raise BDDLError(f"expected one initial placement of {moved[1]} in (:init ...)")
            init = [moved, *kept]
        set_section(problem, ":init", init)
        return dumps(problem)


def _step_key(step: Step) -> str:
    """ "place wine_bottle_1", "open top", "turn_on": an operator and what it moves."""
    return " ".join([step.operator, *(v for k, v in step.arguments if k in ("obj", "drawer"))])


@cache
def published_tasks() -> tuple[tuple[str, str], ...]:
    """(view, label) of the 321 published tasks, in the manifest's order."""
    by_key = {key: view for view, key in VIEWS.items()}
    rows = []
    for line in TASK_LIST.read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            key, label = line.split("|", 1)
            rows.append((by_key[key], label))
    return tuple(rows)


@cache
def second_step_starts() -> dict[str, str]:
    """Second-step label -> the first step whose end state it starts from. An instruction's k-th published repeat
    (suffix k >= 2) starts from the (k-1)-th first step, in alphabetical order, whose end state allows it;
    "put the wine bottle in the top drawer" starts from the open top drawer. The first steps are the 21 except
    opening the middle drawer and the wine bottle on the rack (no second step starts there in the appendix)."""
    firsts = sorted(label for view, label in published_tasks() if view == "first_step")
    states = [
        f for f in firsts if f not in ("open the middle drawer of the cabinet", "put the wine bottle on the rack")
    ]
    starts = {}
    for view, label in published_tasks():
        if view != "second_step":
            continue
        match = re.fullmatch(r"(.+?) (\d+)", label)
        if match is None:
            if label != "put the wine bottle in the top drawer":
                raise ValueError(f"second-step task {label!r} has no repeat number")
            starts[label] = "open the top drawer"
            continue
        goal = parse_step(match.group(1))
        allowed = [s for s in states if may_follow(parse_step(s), goal)]
        k = int(match.group(2))
        if not 2 <= k <= len(allowed) + 1:
            raise ValueError(f"{label!r}: only {len(allowed)} first steps allow it")
        starts[label] = allowed[k - 2]
    return starts


@dataclass(frozen=True)
class ChainSuite:
    name: str
    train: tuple[ChainTask, ...]
    test: tuple[ChainTask, ...]
    original: bool = False

    def similar_counts(self, task: ChainTask) -> dict:
        """The appendix's count for a held-out chain: training chains with its first step that move the same object
        in their second step, to another place; and whether its second step is a training task from its first
        step's end state, and from another start (the appendix's "diff background object config")."""
        first, second = task.steps
        chains = [t.steps for t in self.train if t.view in ("seen_chains", CANDIDATES)]
        same = sum(s[0] == first and s[1].kwargs["obj"] == second.kwargs["obj"] and s[1] != second for s in chains)
        first_text = _split(task.label)[0]
        singles = [t.start for t in self.train if t.view == "second_step" and t.steps == [second]]
        return {
            "same_first_step_and_object": same,
            "second_step_from_that_state": first_text in singles,
            "second_step_from_another_state": any(start != first_text for start in singles),
        }

    def report(self) -> str:
        views = Counter(t.view for t in (*self.train, *self.test))
        lines = [
            f"{self.name}: {len(self.train)} training tasks, {len(self.test)} held out ("
            + ", ".join(f"{views[v]} {v.replace('_', ' ')}" for v in (*VIEWS, CANDIDATES) if views[v])
            + ")"
        ]
        for task in self.test:
            counts = self.similar_counts(task)
            second = task.steps[1]
            lines.append(f"unseen: {task.label}")
            lines.append(
                f"  training: same first step, same second-step object ({second.kwargs['obj']}), another place "
                f"[{counts['same_first_step_and_object']} tasks]"
            )
            for key, where in (("that_state", "its first step's end state"), ("another_state", "another start")):
                found = counts[f"second_step_from_{key}"]
                lines.append(f"  training: its second step from {where} [{'present' if found else 'not present'}]")
        return "\n".join(lines)


def _chain_suite(name: str, views: tuple[str, ...]) -> ChainSuite:
    """The published tasks of `views` for training and the 10 unseen chains held out."""
    starts = second_step_starts()
    tasks = [ChainTask(label, view, starts.get(label)) for view, label in published_tasks()]
    train = tuple(t for t in tasks if t.view in views)
    return ChainSuite(name, train, tuple(t for t in tasks if t.view == "unseen_chains"))


def chain() -> ChainSuite:
    """LIBERO-Gen Chain: 311 training tasks (first steps, second steps, seen chains) and the 10 unseen chains."""
    return _chain_suite("chain", ("first_step", "second_step", "seen_chains"))


LIBERO_GOAL = (
    "open the middle drawer of the cabinet",
    "open the top drawer and put the bowl inside",
    "push the plate to the front of the stove",
    "put the bowl on the plate",
    "put the bowl on the stove",
    "put the bowl on top of the cabinet",
    "put the cream cheese in the bowl",
    "put the wine bottle on the rack",
    "put the wine bottle on top of the cabinet",
    "turn on the stove",
)
"""LIBERO-Goal's own 10 tasks (LIBERO's file names, in words): 9 of Chain's first steps and one of its seen chains."""


def libero_goal() -> ChainSuite:
    """LIBERO-Goal's own 10 tasks as LIBERO ships them: its problems verbatim, rollouts from its initial states."""
    views = {label: view for view, label in published_tasks()}
    return ChainSuite("libero_goal", tuple(ChainTask(t, views[t]) for t in LIBERO_GOAL), (), original=True)


SECOND_STEP_PLACES = {
    "bowl": ("in front of the stove", "on the cream cheese", "on the plate", "on the stove", "on top of the cabinet"),
    "cream cheese": ("in front of the stove", "in the bowl", "on the plate", "on the stove", "on top of the cabinet"),
    "wine bottle": (
        "in front of the stove", "in the bowl", "on the cream cheese", "on the plate", "on the stove",
        "on top of the cabinet",
    ),
}  # fmt: skip
"""Where a chain's second step may put each object (docs/libero-gen/chain.md's candidate rule); also the home region the
first step vacated, and inside the drawer it opened."""


def chain_candidates() -> list[str]:
    """Every two-step chain the candidate rule (docs/libero-gen/chain.md) allows from the 21 first steps, generated:
    the second step puts an object at one of its :data:`SECOND_STEP_PLACES`, at the home region the first step vacated,
    or inside the drawer it opened, where :func:`may_follow` allows it, and not onto what the first step put in the
    bowl. 228 chains, a superset of the authors' 154 (no rule we know picks those)."""
    firsts = [label for view, label in published_tasks() if view == "first_step"]
    words = {name: w for w, name in OBJECTS.items()}
    chains = []
    for first in firsts:
        step = parse_step(first)
        extra = [f"on the {words[step.moves]} region"] if step.operator == "place" else []  # the vacated home
        extra += ["inside"] if step.operator == "open" else []
        for obj, places in SECOND_STEP_PLACES.items():
            for place in (*places, *extra):
                inside = place == "inside"
                label = f"{first} and put the {obj} inside" if inside else f"{first} and then put the {obj} {place}"
                second = parse_instruction(label)[1]
                onto_the_bowls_load = step.leaves_at == OBJECTS["bowl"] and second.leaves_at == step.moves
                if may_follow(step, second) and not onto_the_bowls_load:
                    chains.append(label)
    return chains


def chain_candidates_suite() -> ChainSuite:
    """Chain generated: the candidate chains (:func:`chain_candidates`) train, except the 10 unseen chains, which are
    held out as in the paper (218 + 10)."""
    test = tuple(ChainTask(label, view) for view, label in published_tasks() if view == "unseen_chains")
    held = {t.label for t in test}
    train = tuple(ChainTask(label, CANDIDATES) for label in chain_candidates() if label not in held)
    return ChainSuite("chain_candidates", train, test)


def chain_no_second_step() -> ChainSuite:
    """The ablation view: Chain without its 146 second-step tasks (165 training tasks, the same 10 held out)."""
    return _chain_suite("chain_no_second_step", ("first_step", "seen_chains"))
