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
