"""The key table in docs/architecture.md (from shared/keys.py) and docs/messages.md (from shared/messages.py) are
generated and must not be stale."""

from __future__ import annotations

from shared import keydoc
from shared.keys import DECLARATIONS, Query, Topic


def test_committed_key_table_is_current():
    assert keydoc.main(["--check"]) == 0, "a generated doc is stale: run python -m shared.keydoc"


def test_every_declaration_has_a_row_with_its_types():
    table = keydoc.table()
    for d in DECLARATIONS:
        assert f"`{d.name}`" in table
        if isinstance(d, Topic) and isinstance(d.type, type):
            assert f"`{d.type.__name__}`" in table
        if isinstance(d, Query) and isinstance(d.reply, type):
            assert d.reply.__name__ in table


def test_no_call_site_names_a_declared_type_again():
    """The bus takes declarations: subscribe/query/serve never get a type argument."""
    import re
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    offenders = []
    for path in [*root.glob("services/**/*.py"), *root.glob("shared/*.py"), *root.glob("benchmarks/*.py")]:
        text = path.read_text()
        target = r"[\w.]+(?:\([^()]*\)[\w.]*)*"
        for pattern in (rf"\.subscribe\({target}, (?:[A-Z]\w*|None)\s*[,)]",
                        rf"\.query\({target}, [^,=]+, (?:[A-Z]\w*|None)\s*[,)]",
                        rf"\.serve\({target}, [\w.]+, (?:[A-Z]\w*|None)\s*[,)]"):
            offenders += [f"{path.relative_to(root)}: {m.group(0)}" for m in re.finditer(pattern, text)]
    assert not offenders, offenders


def test_messages_doc_has_every_message_and_field():
    from shared.messages import MESSAGE_TYPES

    text = keydoc.messages_doc()
    for model in MESSAGE_TYPES:
        assert f"### {model.__name__}\n" in text
        for field in model.model_fields:
            assert f"| `{field}` |" in text, (model.__name__, field)
