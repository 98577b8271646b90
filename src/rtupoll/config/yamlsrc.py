"""YAML with line numbers: a small reader that validates as it walks.

PyYAML's composer keeps each node's position; this module walks the node tree so
every error can say ``file:line: field.path: what is wrong``. Used by the profile
loader and the site configuration loader.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, TypeVar

import yaml

from rtupoll.errors import ProfileError

T = TypeVar("T")


class Node:
    """A YAML node with its file, line and dotted path, and typed accessors."""

    def __init__(self, node: yaml.Node, file: str, path: str, error: type[ProfileError]) -> None:
        self.node, self.file, self.path, self._error = node, file, path, error

    @property
    def line(self) -> int:
        return int(self.node.start_mark.line) + 1

    def fail(self, message: str) -> ProfileError:
        return self._error(message, file=self.file, line=self.line, path=self.path)

    def _child(self, node: yaml.Node, key: str | int) -> Node:
        sub = f"{self.path}[{key}]" if isinstance(key, int) else (
            f"{self.path}.{key}" if self.path else str(key))
        return Node(node, self.file, sub, self._error)

    @property
    def is_mapping(self) -> bool:
        return isinstance(self.node, yaml.MappingNode)

    @property
    def is_list(self) -> bool:
        return isinstance(self.node, yaml.SequenceNode)

    # -- shapes -------------------------------------------------------------
    def mapping(self, allowed: set[str] | None = None,
                required: frozenset[str] | set[str] = frozenset()) -> dict[str, Node]:
        out: dict[str, Node] = {}
        for knode, vnode in self._pairs():
            key = str(knode.value)
            child = self._child(vnode, key)
            if allowed is not None and key not in allowed:
                hint = _closest(key, allowed)
                raise Node(knode, self.file, child.path, self._error).fail(
                    f"unknown key{f' (did you mean {hint!r}?)' if hint else ''}")
            out[key] = child  # a key of the node itself overrides one merged in with <<
        missing = sorted(set(required) - out.keys())
        if missing:
            raise self.fail(f"missing required key {missing[0]!r}")
        return out

    def _pairs(self) -> list[tuple[yaml.Node, yaml.Node]]:
        """Key/value node pairs, YAML merge keys (``<<: *anchor``) resolved, duplicates refused."""
        if not isinstance(self.node, yaml.MappingNode):
            raise self.fail(f"expected a mapping, got {self._kind()}")
        seen: set[str] = set()
        for knode, _ in self.node.value:
            if knode.tag == "tag:yaml.org,2002:merge":
                continue
            if str(knode.value) in seen:
                raise Node(knode, self.file, self.path, self._error).fail(
                    f"duplicate key {knode.value!r}")
            seen.add(str(knode.value))
        _LOADER.flatten_mapping(self.node)
        return list(self.node.value)

    def items(self) -> Iterator[tuple[Node, Node]]:
        """Key and value nodes of a mapping whose keys are data (enum codes, flag bits)."""
        for knode, vnode in self._pairs():
            yield self._child(knode, str(knode.value)), self._child(vnode, str(knode.value))

    def sequence(self) -> list[Node]:
        if not isinstance(self.node, yaml.SequenceNode):
            raise self.fail(f"expected a list, got {self._kind()}")
        return [self._child(n, i) for i, n in enumerate(self.node.value)]

    # -- scalars ------------------------------------------------------------
    def value(self) -> Any:
        if not isinstance(self.node, yaml.ScalarNode):
            raise self.fail(f"expected a single value, got {self._kind()}")
        return _LOADER.construct_object(self.node, deep=True)

    def text(self) -> str:
        """A scalar as written: YAML 1.1 would turn enum names like ON/OFF/NO into booleans."""
        if not isinstance(self.node, yaml.ScalarNode) or self.node.tag == "tag:yaml.org,2002:null":
            raise self.fail(f"expected text, got {self._kind()}")
        return str(self.node.value)

    def integer(self, lo: int | None = None, hi: int | None = None) -> int:
        v = self.value()
        if isinstance(v, str):
            try:
                v = int(v, 0)
            except ValueError:
                raise self.fail(f"expected a whole number, got {v!r}") from None
        if isinstance(v, bool) or not isinstance(v, int):
            raise self.fail(f"expected a whole number, got {v!r}")
        if (lo is not None and v < lo) or (hi is not None and v > hi):
            raise self.fail(f"{v} is outside {lo}..{hi}")
        return v

    def number(self) -> float:
        v = self.value()
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise self.fail(f"expected a number, got {v!r}")
        return float(v)

    def flag(self) -> bool:
        v = self.value()
        if not isinstance(v, bool):
            raise self.fail(f"expected true or false, got {v!r}")
        return v

    def choice(self, options: Callable[[str], T], names: list[str]) -> T:
        v = self.value()
        try:
            return options(str(v))
        except (ValueError, KeyError):
            raise self.fail(f"{v!r} is not one of: {', '.join(names)}") from None

    def _kind(self) -> str:
        if isinstance(self.node, yaml.MappingNode):
            return "a mapping"
        if isinstance(self.node, yaml.SequenceNode):
            return "a list"
        return repr(self.node.value)


_LOADER = yaml.SafeLoader("")
# libyaml's composer keeps the same node marks and is ~10x faster (start-up cost)
_COMPOSER: Any = getattr(yaml, "CSafeLoader", yaml.SafeLoader)


def _closest(key: str, allowed: set[str]) -> str | None:
    import difflib

    m = difflib.get_close_matches(key, sorted(allowed), n=1, cutoff=0.6)
    return m[0] if m else None


def load(path: Path, error: type[ProfileError] = ProfileError) -> Node:
    """Parse a YAML file into a ``Node``; syntax errors carry the file and line."""
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise error(f"cannot read: {exc.strerror}", file=str(path)) from None
    try:
        root = yaml.compose(text, Loader=_COMPOSER)
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark
        line = mark.line + 1 if mark else 0
        raise error(f"YAML syntax: {exc.problem}", file=str(path), line=line) from None
    if root is None:
        raise error("the file is empty", file=str(path))
    return Node(root, str(path), "", error)
