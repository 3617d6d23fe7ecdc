"""Message definitions for the third-party ROS 2 peer: .msg files written from rosbags' Jazzy typestore (the
standard messages, with every nested type), and aermani_msgs' .srv copied as it ships."""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

from rosbags.interfaces import Nodetype
from rosbags.typesys import Stores, get_typestore

from shared.ros2.wire import INTERFACES


def _type_text(desc: Any) -> tuple[str, list[str]]:
    """(.msg type text, nested types it names) of one rosbags field description."""
    kind, rest = desc
    if kind == Nodetype.ARRAY:
        inner, deps = _type_text(rest[0])
        return f"{inner}[{rest[1]}]", deps
    if kind == Nodetype.SEQUENCE:
        inner, deps = _type_text(rest[0])
        return f"{inner}[{'<=' + str(rest[1]) if rest[1] else ''}]", deps
    if kind == Nodetype.NAME:
        pkg, _, name = rest.split("/")
        return f"{pkg}/{name}", [rest]
    base, bound = rest
    return (f"{base}<={bound}" if bound else base), []


def write_definitions(root: Path, types: list[str]) -> Path:
    """`root/<pkg>/msg/<Name>.msg` for `types` and everything they contain; returns root."""
    ts = get_typestore(Stores.ROS2_JAZZY)
    todo, done = list(types), set()
    while todo:
        t = todo.pop()
        if t in done:
            continue
        done.add(t)
        consts, fields = ts.fielddefs[t]
        lines = [f"{ctype} {name}={value}" for name, ctype, value in consts]
        for name, desc in fields:
            text, deps = _type_text(desc)
            lines.append(f"{text} {name}")
            todo.extend(deps)
        pkg, _, name = t.split("/")
        path = root / pkg / "msg" / f"{name}.msg"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    srv = root / "aermani_msgs" / "srv"
    srv.mkdir(parents=True, exist_ok=True)
    for f in (INTERFACES / "aermani_msgs" / "srv").glob("*.srv"):
        shutil.copy(f, srv / f.name)
    return root
