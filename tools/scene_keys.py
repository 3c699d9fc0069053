"""Count the scene's user-facing keys: the leaf fields of wrinkles.scene.Scene, recursively.

Tables (dataclass fields) are walked; a list of tables ([[body.pins]]) counts each of its keys
once; fields not set from a scene (``init=False``, e.g. the resolved ``internals``) are left
out; an expert mapping (``options``) counts as one key. Run: ``.venv/bin/python
tools/scene_keys.py [--list]``.
"""

from __future__ import annotations

import argparse
import dataclasses
import types
import typing
from collections import Counter

from wrinkles.scene import Scene


def leaves(cls: type, prefix: str = "") -> list[str]:
    """Dotted keys of the leaf fields of the dataclass ``cls``."""
    out = []
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        if not f.init:
            continue
        tp = hints[f.name]
        args = typing.get_args(tp)
        options = [a for a in args if a is not type(None)] if typing.get_origin(tp) in (
            typing.Union, types.UnionType) else [tp]
        tables = [a for a in options if dataclasses.is_dataclass(a)]
        items = [a for a in args if dataclasses.is_dataclass(a)]
        if tables:
            out += leaves(tables[0], f"{prefix}{f.name}.")
        elif items:
            out += leaves(items[0], f"{prefix}{f.name}[].")
        else:
            out.append(prefix + f.name)
    return out


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description="Count the scene's user-facing keys.")
    parser.add_argument("--list", action="store_true", help="print every key, one per line")
    args = parser.parse_args()
    keys = leaves(Scene)
    print(len(keys), "keys;", dict(Counter(k.split(".")[0].split("[")[0] for k in keys)))
    if args.list:
        print("\n".join(keys))
