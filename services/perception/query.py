"""Free-text object/surface queries: validation, normalisation and matching against visible labels."""

from __future__ import annotations

import re
import unicodedata
from collections.abc import Sequence
from dataclasses import dataclass, field

from shared.messages import MAX_QUERY_CHARS

# Colour words and the label colours they cover (the sim's SimLabel.color plus everyday names).
COLOR_WORDS: dict[str, frozenset[str]] = {
    "red": frozenset({"red", "crimson"}),
    "crimson": frozenset({"crimson"}),
    "purple": frozenset({"purple", "violet"}),
    "violet": frozenset({"purple", "violet"}),
    "blue": frozenset({"blue", "navy"}),
    "navy": frozenset({"navy"}),
    "cyan": frozenset({"cyan"}),
    "teal": frozenset({"teal"}),
    "green": frozenset({"green", "lime"}),
    "lime": frozenset({"lime"}),
    "orange": frozenset({"orange"}),
    "yellow": frozenset({"yellow"}),
    "pink": frozenset({"pink"}),
    "brown": frozenset({"brown", "wood"}),
    "white": frozenset({"white"}),
    "grey": frozenset({"grey", "silver", "steel", "dark grey"}),
    "gray": frozenset({"grey", "silver", "steel", "dark grey"}),
    "silver": frozenset({"silver", "steel"}),
    "black": frozenset({"black"}),
    "beige": frozenset({"beige"}),
    "olive": frozenset({"olive"}),
}

# Size words choose among several matches by 3D volume.
LARGER = frozenset({"larger", "largest", "bigger", "biggest", "big", "large", "huge", "tall", "taller", "tallest"})
SMALLER = frozenset({"smaller", "smallest", "small", "little", "tiny", "short", "shorter", "shortest"})

# Single words that mean a family of things. "snack" follows the paper's ambiguity suite ("bring me a
# snack" with an apple and a cracker box in view): it names every food item, so several in view is
# "ambiguous" and the policy has to pick one.
FAMILIES: dict[str, frozenset[str]] = {
    "snack": frozenset({"apple", "cracker box", "banana", "orange"}),
    "fruit": frozenset({"apple", "banana", "orange"}),
    "food": frozenset({"apple", "cracker box", "banana", "orange"}),
    "tool": frozenset({"wrench", "screwdriver", "hammer"}),
    "drink": frozenset({"coke can", "soda can", "green bottle"}),
    "soda": frozenset({"coke can", "soda can"}),
    "beverage": frozenset({"coke can", "soda can", "green bottle"}),
}

# Word-level synonyms, applied before matching (plural forms are folded separately).
SYNONYMS: dict[str, str] = {
    "coca": "coke", "cola": "coke", "mug": "cup", "glass": "cup", "tin": "can", "carton": "box",
    "crackers": "cracker", "tissues": "tissue", "kleenex": "tissue", "desk": "table", "bookshelf": "shelf",
    "shelves": "shelf", "worktop": "counter", "countertop": "counter", "basin": "sink", "wood": "wooden",
    "biscuit": "cracker", "biscuits": "cracker", "bin": "box",
}

# Names a query may use even when the segmenter has not seen them yet (the simulator's catalogue and the
# paper's task suites). A query naming one of these that is not in view is "not visible", never a
# different object that happens to share a colour or a head noun.
CATALOG = (
    "red cup", "purple cup", "coke can", "soda can", "tissue box", "green bottle", "apple", "orange", "banana",
    "cracker box", "cardboard box", "small box", "large box", "wrench", "screwdriver", "hammer", "table",
    "round table", "wooden table", "shelf", "sink", "counter", "coffee machine", "floor",
)

# Words that carry no meaning for matching.
STOPWORDS = frozenset({
    "the", "a", "an", "this", "that", "one", "on", "onto", "into", "in", "to", "of", "top", "please", "pick",
    "up", "place", "put", "find", "locate", "it", "some", "surface", "object", "item", "thing", "and", "with",
    "me", "my", "near", "at", "from", "there", "is", "over", "above",
})
SIZE_WORDS = LARGER | SMALLER


class BadQuery(ValueError):
    """A query that cannot be matched at all: empty, too long, control characters, no known word."""


@dataclass(frozen=True)
class Candidate:
    """Something visible (or known) that a query can match."""

    key: int
    """Caller's handle (instance id, segment index)."""
    name: str
    """Canonical label, e.g. "red cup"."""
    category: str = "object"
    """object, surface, furniture or structure."""
    color: str = ""
    """Dominant colour name, when known."""
    volume: float = 0.0
    """3D volume in m^3 (for size words)."""


@dataclass(frozen=True)
class Query:
    """A parsed object query: its words, colour words and size selector (larger / smaller)."""

    text: str
    words: tuple[str, ...]
    colors: frozenset[str] = field(default_factory=frozenset)
    size: str | None = None  # "larger" / "smaller"


@dataclass(frozen=True)
class Match:
    """Result of matching: the chosen candidate, or why not."""

    chosen: Candidate | None
    reason: str  # ok, not_visible, ambiguous
    message: str
    matches: tuple[Candidate, ...] = ()


def _fold(word: str) -> str:
    word = SYNONYMS.get(word, word)
    if len(word) > 3 and word.endswith("es") and word[:-2] in ("box", "glass"):
        word = word[:-2]
    elif len(word) > 3 and word.endswith("s") and not word.endswith("ss"):
        word = word[:-1]
    return SYNONYMS.get(word, word)


def clean(text: str) -> str:
    """The query as it is echoed back: control characters removed, whitespace collapsed, 200 chars max."""
    text = "".join(c for c in str(text) if unicodedata.category(c)[0] != "C" or c in " \t")
    return " ".join(text.split())[:MAX_QUERY_CHARS]


def parse(text: str) -> Query:
    """Validate and tokenise a query; raises BadQuery with a message written for the caller."""
    if not isinstance(text, str):
        raise BadQuery("the query must be a string")
    if not text.strip():
        raise BadQuery("the query is empty: name an object (e.g. 'red cup') or a surface (e.g. 'table')")
    if len(text) > MAX_QUERY_CHARS:
        raise BadQuery(f"the query is {len(text)} characters long; at most {MAX_QUERY_CHARS} are accepted")
    if any(unicodedata.category(c) == "Cc" and c not in " \t" for c in text):
        raise BadQuery("the query contains control characters; send plain text such as 'green bottle'")
    raw = re.findall(r"[a-z]+", text.lower())
    words = tuple(_fold(w) for w in raw if w not in STOPWORDS)
    colors = frozenset().union(*(COLOR_WORDS[w] for w in words if w in COLOR_WORDS)) if words else frozenset()
    size = None
    if any(w in LARGER for w in words):
        size = "larger"
    elif any(w in SMALLER for w in words):
        size = "smaller"
    return Query(clean(text), words, colors, size)


def _label_words(name: str) -> tuple[str, ...]:
    return tuple(_fold(w) for w in re.findall(r"[a-z]+", name.lower()))


def words(text: str) -> tuple[str, ...]:
    """Every word of `text` as matching reads it (lower case, synonyms and plurals folded, stopwords kept), for
    callers that find object names in free text (the evaluation's grounding check)."""
    return _label_words(text)


def vocabulary(names: Sequence[str]) -> frozenset[str]:
    """Every word a query may use to refer to one of `names`."""
    words: set[str] = set(COLOR_WORDS) | set(SIZE_WORDS) | set(FAMILIES)
    for n in names:
        words.update(_label_words(n))
    return frozenset(words)


def _score(name: str, qset: set[str]) -> int:
    """How a query's words name a label: 3 full name, 2 family, 1 head noun (or colour-only match), 0 none."""
    lw = _label_words(name)
    if lw and set(lw) <= qset:
        return 3
    if any(name in FAMILIES.get(w, ()) for w in qset):
        return 2
    if lw and (lw[-1] in qset or any(w in qset for w in lw if w not in COLOR_WORDS and w not in SIZE_WORDS)):
        return 1
    return 0


def _filter_colors(names_in: list[str], colors_of: dict[str, str], colors: frozenset[str]) -> list[str]:
    """The names whose colour (or a colour word in their label) the query asks for; all when it names none."""
    if not colors:
        return names_in
    out = []
    for n in names_in:
        c = colors_of.get(n, "")
        if c in colors or set(_label_words(n)) & set(colors):
            out.append(n)
    return out


def match(query: Query, candidates: Sequence[Candidate], known_names: Sequence[str],
          categories: Sequence[str] = ("object",)) -> Match:
    """Choose the candidate a query means.

    Order of evidence: a label named in full ("large box", "round table") beats a head noun ("box",
    "table"); a family word ("snack", "soda") covers several labels; colour words filter; size words pick
    the largest/smallest by 3D volume. Several matches left with no way to choose -> "ambiguous". A query
    whose words name something known but not among `candidates` -> "not visible". A query with no known
    word raises BadQuery."""
    names = sorted(set(known_names) | set(CATALOG) | {c.name for c in candidates})
    vocab = vocabulary(names)
    meaningful = [w for w in query.words if w in vocab]
    if not meaningful:
        unknown = ", ".join(query.words[:5]) or query.text[:40]
        raise BadQuery(f"no known object or surface in the query ({unknown}); known: {', '.join(names[:30])}")
    qset = set(query.words)

    # Which known names does the query mean (independent of visibility)?
    colors_of = {c.name: c.color for c in candidates}
    scored = {n: _score(n, qset) for n in names}
    best = max(scored.values(), default=0)
    if best == 0 and query.colors:
        # "the red one": colour alone names every thing of that colour.
        meant = _filter_colors(names, colors_of, query.colors)
    else:
        meant = [n for n, s in scored.items() if s == best and s > 0]
        if best == 3:
            # "round table" names both "round table" and "table" in full: the more specific name wins.
            sets = {n: set(_label_words(n)) for n in meant}
            meant = [n for n in meant if not any(sets[n] < sets[m] for m in meant)]
        if best < 3:
            meant = _filter_colors(meant, colors_of, query.colors)
    if not meant:
        return Match(None, "not_visible", f"nothing known matches '{query.text}'")

    visible = [c for c in candidates if c.name in meant]
    in_cat = [c for c in visible if c.category in categories]
    if in_cat:
        visible = in_cat
    if not visible:
        return Match(None, "not_visible", f"no {' or '.join(sorted(meant)[:6])} in view")
    if len(visible) == 1:
        return Match(visible[0], "ok", f"matched {visible[0].name}", tuple(visible))
    if query.size is not None and best < 3 or (query.size is not None and len({c.name for c in visible}) == 1):
        chosen = (max if query.size == "larger" else min)(visible, key=lambda c: c.volume)
        return Match(chosen, "ok", f"{query.size} of {len(visible)}: {chosen.name}", tuple(visible))
    labels = ", ".join(sorted({c.name for c in visible}))
    return Match(None, "ambiguous", f"'{query.text}' matches several things in view ({labels}); "
                 "say which (a colour, a full name, or 'larger'/'smaller')", tuple(visible))
