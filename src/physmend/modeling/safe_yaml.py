"""YAML read from a file or a store, bounded before it is built.

``yaml.safe_load`` already refuses tags that construct objects (``!!python/object``), but it builds
whatever the aliases say: a few nested anchors (``&a [*b, *b, …]``) expand to gigabytes from under
a kilobyte. A file physmend did not write itself is read here instead: its size is checked before
parsing, an alias is refused (physmend never writes one), and every error is one line naming the
file and what was expected.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml

#: bytes at most of a YAML file physmend reads as data (a config or a corrections file is a few KB)
MAX_BYTES = 1_000_000
#: nested lists and mappings at most (a configuration nests a few levels; PyYAML builds nesting by
#: recursion, so a deeper file would end in Python's recursion limit)
MAX_NESTING = 100


def load_bounded(path: str | Path, error: type[Exception], *, where: str | None = None,
                 max_bytes: int = MAX_BYTES) -> Any:
    """The data of the YAML file ``path``, or ``error`` (one line naming ``where`` or the file).

    Refused: a file larger than ``max_bytes``; an alias (``*name``); nesting deeper than
    :data:`MAX_NESTING`; a tag that constructs an object; text that is not YAML."""
    path = Path(path)
    label = where or str(path)
    try:
        size = path.stat().st_size
    except OSError as exc:
        raise error(f"{label}: cannot be read ({exc.strerror})") from None
    if size > max_bytes:
        raise error(f"{label}: a YAML file read as data may hold at most {max_bytes} bytes, but holds {size}")
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise error(f"{label}: cannot be read as UTF-8 text ({type(exc).__name__})") from None
    return loads_bounded(text, error, where=label)


def loads_bounded(text: str, error: type[Exception], *, where: str = "YAML") -> Any:
    """:func:`load_bounded` for text already in memory (at most :data:`MAX_BYTES` characters)."""
    if len(text) > MAX_BYTES:
        raise error(f"{where}: a YAML text read as data may hold at most {MAX_BYTES} characters, but holds {len(text)}")
    try:
        depth = 0
        for event in yaml.parse(text, Loader=yaml.SafeLoader):
            if isinstance(event, yaml.AliasEvent):
                raise error(f"{where}: holds a YAML alias (*{str(event.anchor)[:40]}); aliases are refused in files "
                            "read as data (they can expand without bound)")
            if isinstance(event, yaml.CollectionStartEvent):
                depth += 1
                if depth > MAX_NESTING:
                    raise error(f"{where}: nests lists or mappings more than {MAX_NESTING} levels deep "
                                f"(line {event.start_mark.line + 1}); a file read as data may nest at most {MAX_NESTING}")
            elif isinstance(event, yaml.CollectionEndEvent):
                depth -= 1
        return yaml.safe_load(text)
    except RecursionError:
        raise error(f"{where}: nests too deeply to be read (at most {MAX_NESTING} levels)") from None
    except yaml.YAMLError as exc:
        first = str(exc).replace("\n", " ")[:150]
        raise error(f"{where}: is not valid YAML for physmend ({first})") from None
