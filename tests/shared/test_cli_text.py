"""Model and peer text printed on a terminal: markup shown as written, control and invisible characters gone."""

from __future__ import annotations

import io

from rich.console import Console

from shared.text import terminal_text, well_formed


def _printed(text: str) -> str:
    out = io.StringIO()
    Console(file=out, force_terminal=False, width=200).print(f"[dim]{terminal_text(text)}[/dim]")
    return out.getvalue().rstrip("\n")


def test_markup_in_model_text_is_shown_not_interpreted() -> None:
    assert _printed("close [/dim] then [bold]x[/bold] [red]") == "close [/dim] then [bold]x[/bold] [red]"


def test_control_bidi_and_zero_width_characters_are_removed() -> None:
    assert _printed("a\x1b[2Jb\u202ec\u200bd\u2066e\r\nf\x07") == "a[2Jbcdef"


def test_lone_surrogates_are_replaced_and_pairs_kept() -> None:
    assert well_formed("half \ud83d emoji") == "half \ufffd emoji"
    assert well_formed("whole \ud83d\ude00") == "whole \U0001f600"
    assert well_formed("plain") == "plain"
    assert _printed("x\ud83dy") == "x\ufffdy"


def test_plain_text_keeps_lines_only_when_asked() -> None:
    from shared.text import plain_text

    assert plain_text("a\x1b[31m\nb\u202e [/dim]") == "a[31mb [/dim]"
    assert plain_text("a\x1b[31m\nb\u202e [/dim]", lines=True) == "a[31m\nb [/dim]"


def test_a_message_holding_a_lone_surrogate_is_published_with_it_replaced() -> None:
    """A string a peer put in a message (an HTTP client's `\\ud83d`) cannot fail the publish: pydantic's JSON
    writer refuses it, the bus writes the message with U+FFFD instead; nothing else in the message changes."""
    from shared.bus import encode
    from shared.messages import SkillState, SkillStatus

    st = SkillStatus(goal_id="g", skill="grasp", state=SkillState.FAILED, message="half \ud83d emoji", task_id="t",
                     step=1, argument="red cup")
    data, enc = encode(st)
    back = SkillStatus.model_validate_json(data)
    assert back.message == "half \ufffd emoji" and "SkillStatus" in str(enc)
    assert back.model_dump(exclude={"message"}) == st.model_dump(exclude={"message"})
    assert encode(back)[0] == back.model_dump_json().encode()  # the usual path for well-formed text
