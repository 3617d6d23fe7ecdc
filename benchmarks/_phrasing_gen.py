"""Paraphrase generator for the rules parser's dev-side benchmark (issue 33): commands with their expected parse.

Templates x synonyms x word orders over the simulator's catalogue (services/sim/layout.py: the graspable
objects and the surfaces that hold them) and the names people use for them (services/perception/query.py's
word synonyms: "mug" for cup, "worktop" for counter, "kleenex" for tissue...). Every row is one JSONL line in
the schema benchmarks/parser_accuracy.py reads, plus a `construction` tag (also its `kind`). The expected parse
comes from the template's slots, never from the parser: the object and surface chosen for a slot are the
expected target and destination (their catalogue names), a motion slot carries the skills its amount asks for
at the executor's step sizes (45 deg yaw, 0.5 m horizontal, 0.3 m vertical).

Deterministic: `generate(n, seed)` returns the same rows for the same arguments, on any machine. Development
data only; the held-out phrasings are never read here. Not a benchmark itself (the leading underscore keeps
`run_all.py` from running it); `benchmarks/parser_accuracy.py --generated N [--seed S]` scores it.

    .venv/bin/python benchmarks/_phrasing_gen.py 20 --seed 3      # print 20 rows as JSONL
"""

from __future__ import annotations

import argparse
import json
import random
import sys
from collections.abc import Callable
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from services.perception.query import SYNONYMS  # noqa: E402
from services.sim.layout import OBJECTS, SURFACES  # noqa: E402

YAW_STEP_DEG = 45.0  # the executor's default step sizes (services/executor settings; the parser uses the same)
HORIZONTAL_STEP_M = 0.5
VERTICAL_STEP_M = 0.3

CONSTRUCTIONS = ("plain", "telegraphic", "passive", "polite", "ignore_list", "motion", "conditional", "sequence",
                 "search", "non_object_noun")
"""Every construction the generator covers (issue 33's list), in the order rows are dealt."""

# Words a person uses for a catalogue word, read off perception's synonym table (those that read naturally
# inside a name: "bin" for a box or "wood" alone are left out) plus word orders the parser must undo.
_SKIP_ALIASES = {"bin", "coca", "biscuits", "shelves", "crackers", "tissues", "wood"}
ALIASES: dict[str, tuple[str, ...]] = {}
for _alias, _word in sorted(SYNONYMS.items()):
    if _alias not in _SKIP_ALIASES:
        ALIASES[_word] = (*ALIASES.get(_word, ()), _alias)
_REORDERED = {"cracker box": ("box of crackers",), "tissue box": ("box of tissues",), "coke can": ("can of coke",),
              "soda can": ("can of soda",), "wooden table": ("wood table",), "counter": ("kitchen counter",)}

PICK = ("pick up", "grab", "take", "get", "fetch", "collect", "retrieve", "lift", "snag", "grasp", "nab")
PLACE = ("put", "place", "set", "drop", "leave", "lay", "stick", "deposit", "put down", "set down")
CARRY = ("bring", "carry", "move", "take", "transfer", "deliver")
FIND = ("find", "locate", "look for", "search for", "track down", "hunt for", "spot")
GERUND = {"pick up": "picking up", "grab": "grabbing", "take": "taking", "get": "getting", "fetch": "fetching",
          "collect": "collecting", "retrieve": "retrieving", "lift": "lifting", "snag": "snagging",
          "grasp": "grasping", "nab": "nabbing", "put": "putting", "place": "placing", "set": "setting",
          "drop": "dropping", "leave": "leaving", "lay": "laying", "stick": "sticking", "deposit": "depositing",
          "put down": "putting down", "set down": "setting down", "bring": "bringing", "carry": "carrying",
          "move": "moving", "transfer": "transferring", "deliver": "delivering"}
NOT_OBJECT_ONLY = ("pick up the pace", "take a break", "find the answer", "get some rest", "take a deep breath",
                   "take your time", "find a solution", "take a guess", "grab a chance to rest", "find your balance",
                   "get the idea", "take a moment", "get some sleep", "take the initiative")
"""Commands whose only nouns cannot be anything in a room: nothing to look for, no motion: not understood."""


class Row(dict):  # type: ignore[type-arg]
    """One phrasing line; a dict so it dumps as the JSONL schema."""


def _row(construction: str, command: str, target: str | None = None, destination: str | None = None,
         motions: list[str] | None = None, excluded: list[str] | None = None, choices: list[str] | None = None,
         understood: bool = True) -> Row:
    return Row(command=command, kind=construction, construction=construction, target=target, destination=destination,
               motions=list(motions or []), selector=None, group=None, category=None, excluded=list(excluded or []),
               choices=list(choices or []), understood=understood)


class Slots:
    """Draws the slot fillers of one template from the seeded generator: what is said, and what it names."""

    def __init__(self, rng: random.Random) -> None:
        self.rng = rng
        self.used: set[str] = set()

    def pick(self, seq: tuple[str, ...] | list[str]) -> str:
        return self.rng.choice(list(seq))

    def _say(self, name: str) -> str:
        """A way a person names catalogue thing `name`: as listed, one word swapped for an alias, or reordered."""
        options = [name, *_REORDERED.get(name, ())]
        words = name.split()
        for i, w in enumerate(words):
            options += [" ".join([*words[:i], a, *words[i + 1:]]) for a in ALIASES.get(w, ())]
        return self.rng.choice(options) if self.rng.random() < 0.5 else name

    def obj(self) -> tuple[str, str]:
        """(what is said, catalogue name) of a graspable object not used yet in this command."""
        name = self.rng.choice([n for n in OBJECTS if n not in self.used])
        self.used.add(name)
        return self._say(name), name

    def surface(self) -> tuple[str, str, str]:
        """(what is said, catalogue name, a preposition that puts something there)."""
        name = self.rng.choice([n for n in SURFACES if n not in self.used])
        self.used.add(name)
        prep = self.pick(("in", "into") if name == "sink" else ("on", "onto", "on top of"))
        return self._say(name), name, prep

    def motion(self) -> tuple[str, list[str]]:
        """(a motion phrase, the skills it asks for): directions, turns, with and without counts or distances."""
        kind = self.rng.random()
        if kind < 0.08:
            return self.pick((("turn around", ["yaw_left"] * 4), ("take two steps forward", ["forward"] * 2),
                              ("take a step back", ["backward"]), ("back up", ["backward"]),
                              ("go higher", ["up"]), ("move to the left a bit", ["left"]),
                              ("move to the right", ["right"]), ("rise a little", ["up"]),
                              ("turn to the left", ["yaw_left"]), ("take three steps to the right", ["right"] * 3)))
        if kind < 0.3:
            d, skill = self.pick((("left", "yaw_left"), ("right", "yaw_right")))
            amount, n = self.pick((("", 1), (" a bit", 1), (" once", 1), (" twice", 2), (" two times", 2),
                                   (" 90 degrees", 2), (" 45 degrees", 1), (" ninety degrees", 2), (" 180 degrees", 4),
                                   (" three times", 3)))
            verb = self.pick(("turn", "rotate", "yaw", "spin"))
            if amount.endswith("degrees") and self.rng.random() < 0.5:
                return f"{verb}{amount} to the {d}", [skill] * n
            return f"{verb} {d}{amount}", [skill] * n
        if kind < 0.45:
            d, skill = self.pick((("up", "up"), ("down", "down")))
            verb = self.pick(("go", "fly", "move"))
            amount, metres = self.pick((("", None), (" a bit", None), (" a little", None), (" twice", 2),
                                        (" 30 cm", 0.3), (" 60 cm", 0.6), (" one metre", 1.0), (" 1 m", 1.0),
                                        (" 2 m", 2.0), (" two meters", 2.0), (" half a metre", 0.5)))
            n = 1 if metres is None else 2 if amount == " twice" else max(1, round(metres / VERTICAL_STEP_M))
            if amount == "" and self.rng.random() < 0.5:
                return self.pick(("ascend", "climb") if d == "up" else ("descend",)), [skill]
            return f"{verb} {d}{amount}", [skill] * n
        d, skill = self.pick((("forward", "forward"), ("ahead", "forward"), ("back", "backward"),
                              ("backward", "backward"), ("left", "left"), ("right", "right")))
        # "go ahead and ..." is a polite idiom, not a motion: "go ahead" is said with an amount only
        verb = self.pick(("move", "fly", "head") if d == "ahead" else ("move", "fly", "go", "head")
                         if d not in ("left", "right") else ("move", "fly", "strafe",
                                                                                          "slide"))
        amount, count, metres = self.pick((("", 1, None), (" a bit", 1, None), (" a little", 1, None),
                                           (" slightly", 1, None), (" twice", 2, None), (" three times", 3, None),
                                           (" once", 1, None), (" 1 m", None, 1.0), (" one metre", None, 1.0),
                                           (" three metres", None, 3.0), (" 2 m", None, 2.0),
                                           (" 1.5 meters", None, 1.5), (" two metres", None, 2.0),
                                           (" half a metre", None, 0.5), (" 3 m", None, 3.0)))
        n = count if metres is None else max(1, round(metres / HORIZONTAL_STEP_M))
        if metres is not None and self.rng.random() < 0.4:
            return f"{verb}{amount} {d}", [skill] * n
        return f"{verb} {d}{amount}", [skill] * n


def _it(verb: str) -> str:
    """"put down" + it -> "put it down" (the pronoun goes before the particle)."""
    head, _, particle = verb.partition(" ")
    return f"{head} it {particle}" if particle else f"{verb} it"


def _cap(text: str, rng: random.Random) -> str:
    """Mostly sentence case, sometimes all lower case, sometimes with a full stop."""
    out = text[0].upper() + text[1:] if rng.random() < 0.7 else text
    if rng.random() < 0.3 and not out.endswith(("?", ".", "!")):
        out += "."
    return out


Template = Callable[[Slots], Row]


def _plain(s: Slots) -> Row:
    o, on = s.obj()
    d, dn, prep = s.surface()
    src = s.surface()[0]  # where the object stands now: never the destination
    pick, place, carry = s.pick(PICK), s.pick(PLACE), s.pick(CARRY)
    to = "into" if dn == "sink" and s.rng.random() < 0.5 else s.pick(("to", "over to", "onto"))
    forms = [
        (f"{pick} the {o} and {_it(place)} {prep} the {d}", on, dn),
        (f"{pick} the {o}, then {_it(place)} {prep} the {d}", on, dn),
        (f"{carry} the {o} {to} the {d}", on, dn),
        (f"{place.split()[0]} the {o} {prep} the {d}", on, dn),
        (f"{pick} the {o}", on, None),
        (f"{pick} the {o} and then {_it(place)} {prep} the {d}", on, dn),
        (f"{pick} the {o} off the {src} and {_it(place)} {prep} the {d}", on, dn),
        (f"take the {o} from the {src} to the {d}", on, dn),
        (f"{place.split()[0]} the {o} that is on the {src} {prep} the {d}", on, dn),
        (f"pick the {o} up and {_it(place)} {prep} the {d}", on, dn),
        (f"pick the {o} up", on, None),
        (f"the {o}: {pick} it and {_it(place)} {prep} the {d}", on, dn),
        (f"{place.split()[0]} the {o} down {prep} the {d}", on, dn),
        (f"get the {o} onto the {d}", on, dn),
    ]
    cmd, t, dest = forms[s.rng.randrange(len(forms))]
    return _row("plain", cmd, t, dest)


def _telegraphic(s: Slots) -> Row:
    o, on = s.obj()
    d, dn, prep = s.surface()
    the = s.pick(("the ", ""))
    forms = [
        (f"{the}{o} to {the}{d}", dn),
        (f"{the}{o} {prep} {the}{d} please", dn),
        (f"{the}{o} {prep} {the}{d}", dn),
        (f"{the}{o} to the {d}, thanks", dn),
        (f"{the}{o} onto {the}{d}, please", dn),
        (f"{the}{o} over to the {d}", dn),
        (f"{the}{o}, please", None),
        (f"just the {o}", None),
        (f"{the}{o} to the {d} asap", dn),
        (f"{the}{o} into the {d}" if dn == "sink" else f"{the}{o} onto the {d} now", dn),
        (f"{o} -> {d}", dn),
        (f"{the}{o} back to the {d}", dn),
    ]
    cmd, dest = forms[s.rng.randrange(len(forms))]
    return _row("telegraphic", cmd, on, dest)


def _passive(s: Slots) -> Row:
    o, on = s.obj()
    d, dn, prep = s.surface()
    forms = [
        f"the {o} should be put {prep} the {d}",
        f"the {o} needs to go {prep} the {d}",
        f"the {o} must be placed {prep} the {d}",
        f"the {o} has to be moved to the {d}",
        f"the {o} should be moved {prep} the {d}",
        f"the {o} is to be put {prep} the {d}",
        f"I want the {o} placed {prep} the {d}",
        f"I'd like the {o} put {prep} the {d}",
        f"the {o} ought to be set {prep} the {d}",
        f"the {o} should end up {prep} the {d}",
        f"the {o} belongs {prep} the {d}",
        f"the {o} should be taken to the {d}",
        f"the {o} is to go {prep} the {d}",
        f"I need the {o} {prep} the {d}",
        f"I want the {o} {prep} the {d}",
        f"the {o} would be better {prep} the {d}",
        f"the {o} can be put {prep} the {d}",
        f"the {o} needs to be carried to the {d}",
        f"the {o} is supposed to be {prep} the {d}",
        f"have the {o} put {prep} the {d}",
        f"make the {o} go to the {d}",
        f"get the {o} moved {prep} the {d}",
        f"have the {o} brought to the {d}",
    ]
    return _row("passive", forms[s.rng.randrange(len(forms))], on, dn)


def _polite(s: Slots) -> Row:
    o, on = s.obj()
    d, dn, prep = s.surface()
    pick, place, carry = s.pick(PICK), s.pick(PLACE), s.pick(CARRY)
    forms = [
        (f"could you {pick} the {o} and {_it(place)} {prep} the {d}?", dn),
        (f"please {pick} the {o}", None),
        (f"{pick} the {o}, please", None),
        (f"would you mind {GERUND[pick]} the {o}?", None),
        (f"would you mind {GERUND[carry]} the {o} to the {d}?", dn),
        (f"can you {carry} the {o} to the {d} for me?", dn),
        (f"I'd like you to {pick} the {o}", None),
        (f"would you please {place.split()[0]} the {o} {prep} the {d}", dn),
        (f"if you could {pick} the {o}, that would be great", None),
        (f"kindly {carry} the {o} to the {d}", dn),
        (f"do me a favour and {pick} the {o}", None),
        (f"hey drone, could you {pick} the {o} please?", None),
        (f"please {carry} the {o} to the {d}, thank you", dn),
        (f"I would appreciate it if you could {place.split()[0]} the {o} {prep} the {d}", dn),
        (f"would you be so kind as to {pick} the {o}?", None),
        (f"I'd be grateful if you could {carry} the {o} to the {d}", dn),
        (f"when you get a chance, {pick} the {o}", None),
        (f"could you possibly {pick} the {o} for me?", None),
        (f"hey robot, please {carry} the {o} to the {d}, thanks", dn),
        (f"{pick} the {o} for me, would you?", None),
        (f"mind {GERUND[pick]} the {o}?", None),
    ]
    cmd, dest = forms[s.rng.randrange(len(forms))]
    return _row("polite", cmd, on, dest)


def _ignore_list(s: Slots) -> Row:
    o, on = s.obj()
    x, xn = s.obj()
    z, zn = s.obj()
    w, wn = s.obj()
    pick = s.pick(PICK)
    forms = [
        (f"ignore the {x} and {pick} the {o}", [xn]),
        (f"ignore the {x} and the {z}, {pick} the {o}", [xn, zn]),
        (f"{pick} the {o} but leave the {x} alone", [xn]),
        (f"don't touch the {x} or the {z}; {pick} the {o}", [xn, zn]),
        (f"do not touch the {x}, {pick} the {o}", [xn]),
        (f"leave the {x} and the {z} where they are and {pick} the {o}", [xn, zn]),
        (f"{pick} the {o}, ignoring the {x}", [xn]),
        (f"{pick} the {o}, not the {x}", [xn]),
        (f"ignore the {x}, the {z}; just {pick} the {o}", [xn, zn]),
        (f"leave the {x} alone and {pick} the {o}", [xn]),
        (f"{pick} the {o} and don't touch the {x}", [xn]),
        (f"never mind the {x}, {pick} the {o}", [xn]),
        (f"{pick} the {o}, but ignore the {x}", [xn]),
        (f"avoid the {x} and {pick} the {o}", [xn]),
        (f"don't grab the {x}, {pick} the {o}", [xn]),
        (f"skip the {x} and the {z} and {pick} the {o}", [xn, zn]),
        (f"ignore the {x}, the {z} and the {w}, then {pick} the {o}", [xn, zn, wn]),
        (f"{pick} the {o} and leave the {x} and the {z} alone", [xn, zn]),
        (f"{pick} the {o} rather than the {x}", [xn]),
    ]
    cmd, excl = forms[s.rng.randrange(len(forms))]
    return _row("ignore_list", cmd, on, excluded=excl)


def _motion(s: Slots) -> Row:
    m1, k1 = s.motion()
    if s.rng.random() < 0.55:
        return _row("motion", m1, motions=k1)
    m2, k2 = s.motion()
    join = s.pick((" and ", ", then ", " and then ", ", after that ", ". Then "))
    return _row("motion", f"{m1}{join}{m2}", motions=k1 + k2)


def _conditional(s: Slots) -> Row:
    a, an = s.obj()
    b, bn = s.obj()
    d, dn, prep = s.surface()
    pick = s.pick(PICK)
    pick2 = s.pick(PICK)
    a_ = "an" if a[0] in "aeiou" else "a"
    forms = [
        (f"if you see the {a}, {pick} it; otherwise {pick2} the {b}", [an, bn], None, None),
        (f"{pick} the {a} if you see one, otherwise {pick2} the {b}", [an, bn], None, None),
        (f"if there is {a_} {a}, {pick} it, else {pick2} the {b}", [an, bn], None,
         None),
        (f"if you can find the {a}, {pick} it; if not, {pick2} the {b}", [an, bn], None, None),
        (f"if you spot the {a}, {pick} it, or else {pick2} the {b}", [an, bn], None, None),
        (f"{pick} the {a} if you see it, else {pick2} the {b}", [an, bn], None, None),
        (f"if you see the {a}, {pick} it and put it {prep} the {d}; otherwise {pick2} the {b}", [an, bn], dn,
         None),
        (f"if you see the {a}, put it {prep} the {d}", [], dn, an),
        (f"if there is {a_} {a}, {pick} it", [], None, an),
        (f"if you find the {a}, bring it to the {d}", [], dn, an),
        (f"should you see the {a}, {pick} it; otherwise {pick2} the {b}", [an, bn], None, None),
        (f"if the {a} is visible, {pick} it, otherwise {pick2} the {b}", [an, bn], None, None),
        (f"{pick} the {a}, or if there isn't one, the {b}", [an, bn], None, None),
        (f"in case there is {a_} {a}, {pick} it; if there is none, {pick2} the {b}", [an, bn], None, None),
        (f"if you cannot find the {a}, {pick2} the {b}; otherwise {pick} the {a}", [an, bn], None, None),
    ]
    cmd, choices, dest, target = forms[s.rng.randrange(len(forms))]
    return _row("conditional", cmd, target, dest, choices=choices)


def _sequence(s: Slots) -> Row:
    o, on = s.obj()
    d, dn, prep = s.surface()
    m1, k1 = s.motion()
    pick, place, find = s.pick(PICK), s.pick(PLACE), s.pick(FIND)
    then = s.pick((", then ", " and then ", " then ", ", and ", ", after that ", " and after that ", ". Then ",
                   ". After that, ", ", next ", " and next "))
    then2 = s.pick((", then ", " and then ", ", after that ", " and "))
    forms = [
        (f"{m1}{then}{pick} the {o}", k1, None),
        (f"{m1}{then}{pick} the {o}{then2}{_it(place)} {prep} the {d}", k1, dn),
        (f"first {m1}{then}{find} the {o}", k1, None),
        (f"{m1}{then}{pick} the {o} and {_it(place)} {prep} the {d}", k1, dn),
    ]
    if s.rng.random() < 0.3:
        m2, k2 = s.motion()
        cmd, ks, dest = f"{m1}, {m2}{then}{pick} the {o}", k1 + k2, None
    elif s.rng.random() < 0.2:
        go = s.pick(("go to", "fly to", "head to", "approach"))
        cmd, ks, dest = f"{go} the {d}{then}{pick} the {o}", [f"approach:{dn}"], None
    else:
        cmd, ks, dest = forms[s.rng.randrange(len(forms))]
    return _row("sequence", cmd, on, dest, motions=ks)


def _search(s: Slots) -> Row:
    o, on = s.obj()
    find = s.pick(FIND)
    forms = [
        f"{find} the {o}",
        f"where is the {o}?",
        f"can you {find} the {o}?",
        f"search the room for the {o}",
        f"look around for the {o}",
        f"see if you can find the {o}",
        f"please {find} the {o}",
        f"I'm looking for the {o}",
        f"have a look for the {o}",
        f"find me the {o}",
        f"do you see the {o}?",
        f"can you spot the {o}?",
        f"is there {'an' if o[0] in 'aeiou' else 'a'} {o} anywhere?",
        f"scan the room for the {o}",
        f"go and find the {o}",
        f"try to locate the {o}",
    ]
    return _row("search", forms[s.rng.randrange(len(forms))], on)


def _non_object(s: Slots) -> Row:
    if s.rng.random() < 0.2:
        return _row("non_object_noun", s.pick(NOT_OBJECT_ONLY), understood=False)
    o, on = s.obj()
    d, dn, prep = s.surface()
    pick, carry = s.pick(PICK), s.pick(CARRY)
    forms = [
        (f"take your time and {pick} the {o}", None),
        (f"in a minute, {pick} the {o}", None),
        (f"{pick} the {o} with care", None),
        (f"{pick} the {o} at your convenience", None),
        (f"for the sake of tidiness, {carry} the {o} to the {d}", dn),
        (f"{pick} the {o} in one go", None),
        (f"use your judgement and {pick} the {o}", None),
        (f"after a short pause, {pick} the {o}", None),
        (f"{pick} the {o} without delay", None),
        (f"with your gripper, {pick} the {o}", None),
        (f"at the first opportunity, {carry} the {o} to the {d}", dn),
        (f"in a moment, {pick} the {o}", None),
        (f"as a favour, {pick} the {o}", None),
        (f"{pick} the {o} in a hurry", None),
        (f"{pick} the {o} when you have a chance", None),
        (f"on my signal, {pick} the {o}", None),
        (f"without any fuss, {carry} the {o} to the {d}", dn),
        (f"for safety, {pick} the {o} slowly", None),
        (f"just to be sure, {pick} the {o}", None),
    ]
    cmd, dest = forms[s.rng.randrange(len(forms))]
    return _row("non_object_noun", cmd, on, dest)


TEMPLATES: dict[str, Template] = {
    "plain": _plain, "telegraphic": _telegraphic, "passive": _passive, "polite": _polite,
    "ignore_list": _ignore_list, "motion": _motion, "conditional": _conditional, "sequence": _sequence,
    "search": _search, "non_object_noun": _non_object,
}
assert tuple(TEMPLATES) == CONSTRUCTIONS


def generate(n: int, seed: int = 0) -> list[Row]:
    """`n` commands with their expected parse, the constructions dealt in turn; the same for the same seed.
    Repeats are redrawn (a few tries) so the set holds as many distinct commands as the templates allow."""
    rng = random.Random(seed)
    rows: list[Row] = []
    seen: set[str] = set()
    for i in range(n):
        construction = CONSTRUCTIONS[i % len(CONSTRUCTIONS)]
        for _try in range(20):
            row = TEMPLATES[construction](Slots(rng))
            row["command"] = _cap(row["command"], rng)
            if row["command"].lower().rstrip(".") not in seen:
                break
        seen.add(row["command"].lower().rstrip("."))
        rows.append(row)
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("n", type=int, nargs="?", default=20, help="how many commands")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    for row in generate(args.n, args.seed):
        print(json.dumps(row))
    return 0


if __name__ == "__main__":
    sys.exit(main())
