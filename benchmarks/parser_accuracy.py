"""Accuracy of the rules baseline's command reader (services/reasoner/backends/rules_parse.py) on phrasing sets.

Each FILE is JSONL, one phrasing per line: {"command", "kind", "target", "destination", "motions", "selector",
"group", "category", "excluded", "choices", "understood"}. A line is correct when every field matches the
parse after normalising (lower case, singular nouns, surrounding spaces and articles dropped, lists compared in
order); an expected `understood: false` only needs the parse to be refused. Prints, per file, accuracy per kind
and overall, then per-field accuracy. Robust to unknown kinds, missing fields (not scored), blank or broken
lines (reported and counted wrong).

`--generated N [--seed S]` also scores N commands from the dev-side paraphrase generator
(benchmarks/_phrasing_gen.py: templates x synonyms x word orders over the simulator's catalogue) and prints
accuracy per construction. There a name counts as the catalogue thing it names through perception's word
synonyms ("red mug" is the red cup, "worktop" the counter), as the policy's perception query resolves it. Run:

    .venv/bin/python benchmarks/parser_accuracy.py tests/reasoner/data/phrasings_dev.jsonl [MORE.jsonl ...]
    [--show-errors] [--generated 2000 [--seed 0]]
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import defaultdict
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks._figures import add_json_option, write_json  # noqa: E402
from benchmarks._phrasing_gen import CONSTRUCTIONS, generate  # noqa: E402
from services.perception.query import SYNONYMS  # noqa: E402
from services.reasoner.backends.rules_parse import parse_command, singular  # noqa: E402

FIELDS = ("target", "destination", "motions", "selector", "group", "category", "excluded", "choices", "understood")


def norm(value: object) -> object:
    """Comparable form of a field value: strings lower-cased, articles dropped, each word singular."""
    if value is None or value == "":
        return None
    if isinstance(value, bool):
        return value
    if isinstance(value, (list, tuple)):
        return [norm(v) for v in value]
    text = " ".join(str(value).lower().replace("_", "_").split())
    if text.startswith("approach:"):
        return "approach:" + str(norm(text[len("approach:"):]))
    words = [w for w in text.split() if w not in ("the", "a", "an")]
    return " ".join(singular(w) for w in words) or None


def same_thing(value: object) -> object:
    """A normalised value with each word replaced by the word perception reads it as ("mug" -> "cup")."""
    if isinstance(value, list):
        return [same_thing(v) for v in value]
    if not isinstance(value, str):
        return value
    head = "approach:" if value.startswith("approach:") else ""
    return head + " ".join(SYNONYMS.get(w, w) for w in value[len(head):].split())


def score_line(row: dict, fold: bool = False) -> tuple[bool, dict[str, bool], dict]:
    """(line correct, per-field correct, the parse) for one phrasing; `fold`: names compared through
    perception's word synonyms (the generated set)."""
    plan = parse_command(str(row.get("command", "")))
    got = plan.as_record()
    fields: dict[str, bool] = {}
    expect_understood = row.get("understood", True)
    for f in FIELDS:
        if f not in row:
            continue
        if f != "understood" and expect_understood is False:
            continue  # a refusal is judged by `understood` alone
        want = norm(row[f]) if f != "understood" else bool(row[f])
        have = norm(got[f]) if f != "understood" else bool(got[f])
        if isinstance(want, list) and not want:
            want = []
        if isinstance(have, list) and not have:
            have = []
        if fold:
            want, have = same_thing(want), same_thing(have)
        fields[f] = want == have
    return all(fields.values()) and bool(fields), fields, got


def _score_rows(rows: list[dict], label: str, group: str, show_errors: bool, fold: bool,
                per_kind: dict[str, list[int]], per_field: dict[str, list[int]]) -> None:
    """Score `rows` into per_kind (by the row's `group` field) and per_field; print the wrong ones if asked."""
    for n, row in rows_numbered(rows):
        kind = str(row.get(group) or "(no kind)")
        ok, fields, got = score_line(row, fold)
        per_kind[kind][0] += ok
        per_kind[kind][1] += 1
        for f, good in fields.items():
            per_field[f][0] += good
            per_field[f][1] += 1
        if show_errors and not ok:
            wrong = {f: (row.get(f), got[f]) for f, good in fields.items() if not good}
            print(f"  WRONG {label}:{n} [{kind}] {row['command']!r}: (expected, parsed) {wrong}")


def rows_numbered(rows: list[dict]) -> list[tuple[int, dict]]:
    return [(int(r.get("_line", i)), r) for i, r in enumerate(rows, 1)]


def _print_table(title: str, column: str, per_kind: dict[str, list[int]], per_field: dict[str, list[int]],
                 order: tuple[str, ...] = ()) -> tuple[int, int]:
    right = sum(v[0] for v in per_kind.values())
    total = sum(v[1] for v in per_kind.values())
    print(f"\n{title}")
    print(f"  {column:<24} {'correct':>8} {'total':>6} {'accuracy':>9}")
    for kind in [k for k in order if k in per_kind] + sorted(k for k in per_kind if k not in order):
        r, t = per_kind[kind]
        print(f"  {kind:<24} {r:>8} {t:>6} {100 * r / t:>8.1f}%")
    print(f"  {'OVERALL':<24} {right:>8} {total:>6} {100 * right / max(total, 1):>8.1f}%")
    print(f"  {'field':<24} {'correct':>8} {'scored':>6} {'accuracy':>9}")
    for f in FIELDS:
        if f in per_field:
            r, t = per_field[f]
            print(f"  {f:<24} {r:>8} {t:>6} {100 * r / t:>8.1f}%")
    return right, total


def evaluate(path: Path, show_errors: bool) -> tuple[int, int]:
    per_kind: dict[str, list[int]] = defaultdict(lambda: [0, 0])
    per_field: dict[str, list[int]] = defaultdict(lambda: [0, 0])
    lines = path.read_text(encoding="utf-8").splitlines()
    bad = 0
    rows: list[dict] = []
    for n, line in enumerate(lines, 1):
        if not line.strip():
            continue
        try:
            row = json.loads(line)
            if not isinstance(row, dict) or "command" not in row:
                raise ValueError("not an object with a command")
        except ValueError as exc:
            bad += 1
            per_kind["(unreadable line)"][1] += 1
            print(f"  {path.name}:{n}: unreadable line, counted wrong ({exc})")
            continue
        rows.append({**row, "_line": n})
    _score_rows(rows, path.name, "kind", show_errors, False, per_kind, per_field)
    total = sum(v[1] for v in per_kind.values())
    return _print_table(f"{path}: {total} phrasings" + (f" ({bad} unreadable)" if bad else ""), "kind", per_kind,
                        per_field)


def evaluate_generated(n: int, seed: int, show_errors: bool) -> dict[str, dict[str, float]]:
    """Score `n` generated dev commands (seed `seed`); -> per construction and "overall": correct, total, %."""
    per_kind: dict[str, list[int]] = defaultdict(lambda: [0, 0])
    per_field: dict[str, list[int]] = defaultdict(lambda: [0, 0])
    _score_rows(generate(n, seed), f"generated(seed {seed})", "construction", show_errors, True, per_kind,
                per_field)
    right, total = _print_table(f"generated dev commands: {n} (seed {seed})", "construction", per_kind, per_field,
                                CONSTRUCTIONS)
    out = {k: {"correct": r, "total": t, "accuracy_pct": 100 * r / max(t, 1)} for k, (r, t) in per_kind.items()}
    out["overall"] = {"correct": right, "total": total, "accuracy_pct": 100 * right / max(total, 1)}
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("files", nargs="*", type=Path, help="JSONL phrasing sets")
    ap.add_argument("--show-errors", action="store_true", help="print every wrong line with the fields that differ")
    ap.add_argument("--generated", type=int, default=0, metavar="N",
                    help="also score N commands from the dev-side paraphrase generator, per construction")
    ap.add_argument("--seed", type=int, default=0, help="the generator's seed (with --generated)")
    add_json_option(ap)
    args = ap.parse_args(argv)
    if not args.files and not args.generated:
        ap.error("give a JSONL file or --generated N")
    right = total = 0
    per_file: dict[str, dict[str, float]] = {}
    for path in args.files:
        if not path.is_file():
            print(f"{path}: no such file", file=sys.stderr)
            return 2
        r, t = evaluate(path, args.show_errors)
        right, total = right + r, total + t
        per_file[path.name] = {"correct": r, "total": t, "accuracy_pct": 100 * r / max(t, 1)}
    if len(args.files) > 1:
        print(f"\nall files: {right}/{total} = {100 * right / max(total, 1):.1f}%")
    figures: dict[str, object] = {"files": per_file, "correct": right, "total": total,
                                  "accuracy_pct": 100 * right / max(total, 1)}
    if args.generated:
        figures["generated"] = evaluate_generated(args.generated, args.seed, args.show_errors)
        figures["generated_seed"] = args.seed
    write_json(args.json, "parser_accuracy", figures, args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
