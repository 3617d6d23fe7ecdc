"""Query parsing and matching: names, synonyms, colours, families, size words, ambiguity, bad input."""

from __future__ import annotations

import pytest

from services.perception import query as q

KNOWN = ["red cup", "purple cup", "coke can", "soda can", "tissue box", "green bottle", "apple", "orange",
         "banana", "cracker box", "cardboard box", "small box", "large box", "wrench", "screwdriver", "hammer",
         "table", "round table", "wooden table", "shelf", "sink", "counter", "coffee machine"]
COLORS = {"red cup": "red", "purple cup": "purple", "coke can": "crimson", "soda can": "blue", "apple": "lime",
          "orange": "orange", "banana": "yellow", "cracker box": "pink", "cardboard box": "brown",
          "small box": "teal", "large box": "navy", "green bottle": "green", "tissue box": "cyan"}
VOLUME = {"small box": 0.0008, "large box": 0.023, "cardboard box": 0.0144, "cracker box": 0.0024,
          "tissue box": 0.0029}


def cands(*names: str) -> list[q.Candidate]:
    cat = {"table": "surface", "round table": "surface", "wooden table": "surface", "shelf": "surface",
           "sink": "surface", "counter": "surface"}
    return [q.Candidate(i, n, cat.get(n, "object"), COLORS.get(n, ""), VOLUME.get(n, 0.001))
            for i, n in enumerate(names)]


def pick(text: str, visible: list[str], categories=("object",)) -> q.Match:
    return q.match(q.parse(text), cands(*visible), KNOWN, categories)


@pytest.mark.parametrize(("text", "visible", "want"), [
    ("red cup", ["red cup", "purple cup"], "red cup"),
    ("the red cup", ["red cup", "coke can"], "red cup"),
    ("Pick up the GREEN bottle!", ["green bottle", "apple"], "green bottle"),
    ("bottle", ["green bottle", "red cup"], "green bottle"),
    ("coke", ["coke can", "red cup"], "coke can"),
    ("coca cola", ["coke can", "soda can"], "coke can"),
    ("soda can", ["coke can", "soda can"], "soda can"),
    ("the blue can", ["coke can", "soda can"], "soda can"),
    ("purple mug", ["red cup", "purple cup"], "purple cup"),
    ("tissues", ["tissue box", "cracker box"], "tissue box"),
    ("the larger box", ["small box", "cardboard box"], "cardboard box"),
    ("the smaller box", ["large box", "cardboard box"], "cardboard box"),
    ("big box", ["small box", "large box", "tissue box"], "large box"),
    ("large box", ["small box", "large box"], "large box"),
    ("small box", ["small box", "large box"], "small box"),
    ("orange", ["orange", "banana"], "orange"),
    ("a snack", ["apple", "red cup"], "apple"),
    ("fruit", ["banana", "hammer"], "banana"),
])
def test_objects_match(text: str, visible: list[str], want: str) -> None:
    m = pick(text, visible)
    assert m.reason == "ok", m.message
    assert m.chosen is not None and m.chosen.name == want


@pytest.mark.parametrize(("text", "visible", "want"), [
    ("table", ["table", "round table", "wooden table"], "table"),
    ("round table", ["table", "round table"], "round table"),
    ("on the wooden table", ["table", "wooden table"], "wooden table"),
    ("the sink", ["sink", "counter"], "sink"),
    ("bookshelf", ["shelf", "sink"], "shelf"),
])
def test_surfaces_match(text: str, visible: list[str], want: str) -> None:
    m = pick(text, visible, ("surface", "furniture"))
    assert m.chosen is not None and m.chosen.name == want, m.message


@pytest.mark.parametrize(("text", "visible"), [
    ("snack", ["apple", "cracker box"]),
    ("cup", ["red cup", "purple cup"]),
    ("soda", ["coke can", "soda can"]),
    ("box", ["tissue box", "small box"]),
])
def test_ambiguous(text: str, visible: list[str]) -> None:
    m = pick(text, visible)
    assert m.chosen is None and m.reason == "ambiguous"
    assert "several" in m.message


@pytest.mark.parametrize(("text", "visible"), [
    ("red cup", ["purple cup", "apple"]),
    ("the larger box", ["red cup"]),
    ("hammer", []),
    ("round table", ["table"]),
])
def test_not_visible(text: str, visible: list[str]) -> None:
    m = pick(text, visible, ("object", "surface"))
    assert m.chosen is None and m.reason == "not_visible"


@pytest.mark.parametrize("text", ["", "   ", "x" * 10_240, "red\x00cup", "red cup\n\x1b[2J", "\u0007"])
def test_bad_input_raises_bad_query(text: str) -> None:
    with pytest.raises(q.BadQuery):
        q.parse(text)


@pytest.mark.parametrize("text", ["flibbertigibbet", "quantum chromodynamics", "12345", "!!!"])
def test_unknown_words_are_bad_queries(text: str) -> None:
    with pytest.raises(q.BadQuery, match="no known object"):
        q.match(q.parse(text), cands("red cup"), KNOWN)


def test_clean_echo_is_bounded_and_printable() -> None:
    assert q.clean("a\x00b\tc  " + "d" * 500) == ("ab c " + "d" * 500)[:200]
