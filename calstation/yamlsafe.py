"""Reading YAML that people wrote by hand, safely: bounded size and depth, no duplicate keys.

PyYAML's composer recurses once per nesting level (20 000 ``[`` end in a ``RecursionError``),
its loader silently lets the last of two equal keys win, and anchors can expand a small file into
a huge tree. :func:`load_yaml` checks all three before building anything, and
:func:`read_text_file` refuses what is not a regular file of bounded size (a FIFO would block
``open()`` forever). Problems are :class:`YamlProblem`: a line (1-based, or None), a field path
and a message, for the caller to format as ``FILE:LINE: field: message``.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path
from typing import Any

import yaml

MAX_DEPTH = 32
"""Deepest nesting of mappings and sequences accepted."""

MAX_NODES = 50_000
"""Most values (scalars, mappings, sequences, counted after anchors are expanded) accepted."""

Loc = tuple[int | str, ...]


class YamlProblem(Exception):
    """A problem in YAML text: its 1-based ``line`` (None if unknown), field path and message."""

    def __init__(self, line: int | None, loc: Loc, message: str) -> None:
        super().__init__(message)
        self.line = line
        self.loc = loc
        self.message = message


def _file_kind(mode: int) -> str:
    for test, name in (
        (stat.S_ISDIR, "folder"),
        (stat.S_ISFIFO, "named pipe (FIFO)"),
        (stat.S_ISSOCK, "socket"),
        (stat.S_ISCHR, "character device"),
        (stat.S_ISBLK, "block device"),
    ):
        if test(mode):
            return name
    return "special file"


def check_regular_file(path: Path, what: str, max_bytes: int) -> int:
    """The size of ``path`` if it is a regular file of at most ``max_bytes``; else OSError-free
    :class:`ValueError` saying what it is (``what`` names it: "recipe", "mesh file")."""
    try:
        st = os.stat(path)
    except FileNotFoundError:
        raise ValueError(f"{what} not found") from None
    except OSError as exc:
        raise ValueError(f"cannot read the {what}: {exc.strerror or exc}") from None
    if not stat.S_ISREG(st.st_mode):
        raise ValueError(f"the {what} is a {_file_kind(st.st_mode)}, not a regular file")
    if st.st_size > max_bytes:
        raise ValueError(
            f"the {what} is {st.st_size / 1e6:.1f} MB, more than the {max_bytes / 1e6:g} MB "
            "calstation accepts"
        )
    return st.st_size


def read_text_file(path: Path, what: str, max_bytes: int) -> str:
    """UTF-8 text of a regular file of at most ``max_bytes``; ValueError says why not."""
    check_regular_file(path, what, max_bytes)
    try:
        # O_NONBLOCK: should the file be swapped for a FIFO after the check, open() still returns
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
        with os.fdopen(fd, "rb") as f:
            if not stat.S_ISREG(os.fstat(f.fileno()).st_mode):
                raise ValueError(f"the {what} is not a regular file")
            data = f.read(max_bytes + 1)
    except OSError as exc:
        raise ValueError(f"cannot read the {what}: {exc.strerror or exc}") from None
    if len(data) > max_bytes:
        raise ValueError(f"the {what} is more than the {max_bytes / 1e6:g} MB calstation accepts")
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = data[: exc.start].count(b"\n") + 1
        raise ValueError(f"line {line}: the {what} is not UTF-8 text ({exc.reason})") from None


MAX_INT_DIGITS = 100
"""Most digits an integer may have (Python refuses to convert past 4300; no setting needs 20)."""

_PARSER = getattr(yaml, "CSafeLoader", yaml.SafeLoader)
"""libyaml's parser when PyYAML has it: the bounds below are checked before anything is built,
and at its speed a file of a hundred thousand values is refused in a tenth of a second (the
pure-Python parser takes seconds)."""


def _line(event: yaml.Event) -> int | None:
    return event.start_mark.line + 1 if event.start_mark else None


def _check_depth(text: str) -> None:
    """Walk the event stream (the parser is not recursive) and bound the nesting and the number
    of values written (anchors expanded are counted by :func:`_check_tree`). Text libyaml
    refuses is walked again by PyYAML's own parser, whose errors say more."""
    try:
        _check_events(text, _PARSER)
    except yaml.YAMLError:
        if _PARSER is yaml.SafeLoader:
            raise
        _check_events(text, yaml.SafeLoader)


def _check_events(text: str, loader: type[yaml.SafeLoader]) -> None:
    depth = values = 0
    for event in yaml.parse(text, Loader=loader):
        if isinstance(event, yaml.MappingStartEvent | yaml.SequenceStartEvent):
            depth += 1
            if depth > MAX_DEPTH:
                raise YamlProblem(
                    _line(event), (),
                    f"nested more than {MAX_DEPTH} levels deep; a recipe is not that deep"
                )
        elif isinstance(event, yaml.MappingEndEvent | yaml.SequenceEndEvent):
            depth -= 1
            continue
        elif not isinstance(event, yaml.ScalarEvent | yaml.AliasEvent):
            continue
        values += 1
        if values > MAX_NODES:
            raise YamlProblem(
                _line(event), (), f"holds more than {MAX_NODES} values; a recipe is smaller"
            )


def _key_text(node: yaml.Node) -> str:
    return str(node.value) if isinstance(node, yaml.ScalarNode) else f"<{type(node).__name__}>"


def _check_tree(root: yaml.Node) -> None:
    """Duplicate keys (naming both lines) and the expanded size of the tree (anchors counted at
    every use)."""
    sizes: dict[int, int] = {}

    def walk(node: yaml.Node, loc: Loc) -> int:
        if id(node) in sizes:  # an alias: its size counts again, its keys were checked
            return sizes[id(node)]
        size = 1
        if isinstance(node, yaml.MappingNode):
            seen: dict[tuple[str, str], int] = {}
            for key, value in node.value:
                line = key.start_mark.line + 1
                if key.tag == "tag:yaml.org,2002:merge":
                    size += walk(value, loc)
                    continue
                ident = (key.tag, _key_text(key))
                if ident in seen:
                    raise YamlProblem(
                        line,
                        (*loc, _key_text(key)),
                        f"duplicate key {_key_text(key)!r} (first at line {seen[ident]}, again at "
                        f"line {line}); a key may appear once",
                    )
                seen[ident] = line
                size += walk(key, loc) + walk(value, (*loc, _key_text(key)))
        elif isinstance(node, yaml.SequenceNode):
            for i, item in enumerate(node.value):
                size += walk(item, (*loc, i))
        elif node.tag == "tag:yaml.org,2002:int" and len(node.value) > MAX_INT_DIGITS:
            raise YamlProblem(
                node.start_mark.line + 1, loc,
                f"an integer of {len(node.value)} characters; no value is written with more "
                f"than {MAX_INT_DIGITS} digits"
            )
        if size > MAX_NODES:
            raise YamlProblem(
                node.start_mark.line + 1,
                loc,
                f"expands to more than {MAX_NODES} values (anchors included); a recipe is smaller",
            )
        sizes[id(node)] = size
        return size

    walk(root, ())


def load_yaml(text: str) -> tuple[Any, yaml.Node | None]:  # Any: yaml's data, untyped
    """Parse ``text``: (the data, its composed node tree for line look-ups).

    Raises :class:`YamlProblem` for text nested deeper than :data:`MAX_DEPTH`, holding a key
    twice in one mapping, or expanding past :data:`MAX_NODES` values; ``yaml.YAMLError`` for text
    that is not YAML.
    """
    _check_depth(text)
    loader = yaml.SafeLoader(text)
    try:
        node = loader.get_single_node()
        if node is None:
            return None, None
        _check_tree(node)
        try:
            return loader.construct_document(node), node
        except ValueError as exc:  # a value Python cannot build, as a last guard
            raise YamlProblem(None, (), f"a value cannot be read: {exc}") from None
    finally:
        loader.dispose()
