"""YAML with line numbers: a small reader that validates as it walks.

PyYAML's composer keeps each node's position; this module walks the node tree so
every error can say ``file:line: field.path: what is wrong``. Used by every loader:
profiles, site files, simulator scenarios and address plans.

Files are untrusted: loading one is bounded in size, nesting depth and node count
(aliases and ``<<`` merge keys counted as expanded), and every way a file can be
wrong (binary, not UTF-8, control characters, unknown tags, ``!!int "abc"``,
``<<: 5``, NaN where a number is wanted) is a ``file:line`` error, never a traceback.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, TypeVar

import yaml

from rtupoll.errors import ProfileError

T = TypeVar("T")

MAX_BYTES = 256 << 10  # a larger file is refused unread (the largest bundled: 9 kB)
MAX_NODES = 100_000  # nodes, with every alias and merge key expanded
MAX_DEPTH = 64  # nested mappings and lists (the deepest bundled file: 5)
# libyaml's composer recurses in C (a crash at ~30,000 levels) and its scanner is quadratic
# in the nesting; below this bound on the depth a file is handed to it unscanned. The
# libyaml in PyYAML 6.0.4's wheels refuses 1,000 levels itself ("exceeded maximum nesting
# depth", often before this check's own words), but the one in 6.0 to 6.0.3 does not, nor
# does PyYAML without libyaml: the check stays while pyproject.toml allows those.
_C_SAFE_DEPTH = 1000
_MERGE = "tag:yaml.org,2002:merge"


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
            if not isinstance(knode, yaml.ScalarNode):  # `? [a, b]`: a list as a key
                raise Node(knode, self.file, self.path, self._error).fail(
                    "a key must be a plain name, not a list or a mapping")
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
            if knode.tag == _MERGE:
                continue
            if str(knode.value) in seen:
                raise Node(knode, self.file, self.path, self._error).fail(
                    f"duplicate key {knode.value!r}")
            seen.add(str(knode.value))
        try:  # bounded: ``load`` counted what merging expands to
            _LOADER.flatten_mapping(self.node)
        except yaml.MarkedYAMLError as exc:
            mark = exc.problem_mark or exc.context_mark
            line = mark.line + 1 if mark else self.line
            raise self._error(f"{exc.problem or exc.context}", file=self.file, line=line,
                              path=self.path) from None
        return list(self.node.value)

    def key(self, name: str) -> Node | None:
        """The value of ``name`` in a mapping ``mapping`` has read (merge keys resolved, so
        the node's own key, listed last, wins); None when it has no such key."""
        found = None
        if isinstance(self.node, yaml.MappingNode):
            for knode, vnode in self.node.value:
                if isinstance(knode, yaml.ScalarNode) and str(knode.value) == name:
                    found = self._child(vnode, name)
        return found

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
        try:
            return _LOADER.construct_object(self.node, deep=True)
        except (yaml.YAMLError, ValueError, KeyError, TypeError, OverflowError):
            tag = str(self.node.tag)
            short = tag.replace("tag:yaml.org,2002:", "!!")
            if tag not in _LOADER.yaml_constructors:
                raise self.fail(f"unsupported tag {short}") from None
            raise self.fail(f"{_brief(self.node.value)} is not a valid {short}") from None
        finally:  # the loader is shared: forget what it built, including a failure
            _LOADER.constructed_objects.clear()
            _LOADER.recursive_objects.clear()

    def text(self) -> str:
        """A scalar as written: YAML 1.1 would turn enum names like ON/OFF/NO into booleans."""
        if not isinstance(self.node, yaml.ScalarNode) or self.node.tag == "tag:yaml.org,2002:null":
            raise self.fail(f"expected text, got {self._kind()}")
        if self.node.tag not in _LOADER.yaml_constructors:  # !!python/..., !custom
            raise self.fail(f"unsupported tag {self.node.tag.replace('tag:yaml.org,2002:', '!!')}")
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

    def number(self, *, finite: bool = True) -> float:
        """A number; NaN and infinities are refused unless ``finite=False``."""
        v = self.value()
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise self.fail(f"expected a number, got {v!r}")
        try:
            f = float(v)
        except OverflowError:
            raise self.fail(f"{v} is too large") from None
        if finite and not math.isfinite(f):
            raise self.fail(f"expected a finite number, got {self.node.value}")
        return f

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
        return _brief(self.node.value)


_LOADER = yaml.SafeLoader("")
# libyaml's composer keeps the same node marks and is ~10x faster (start-up cost)
_COMPOSER: Any = getattr(yaml, "CSafeLoader", yaml.SafeLoader)


def _brief(value: object, width: int = 40) -> str:
    """``repr`` for a message, shortened: a hostile file's scalar may be 200 kB long."""
    text = repr(value)
    return text if len(text) <= width else f"{text[:width - 5]}...{text[-2:]}"


def _closest(key: str, allowed: set[str]) -> str | None:
    from rtupoll.model.names import close_names

    m = close_names(key, sorted(allowed))
    return m[0] if m else None


def load(path: Path, error: type[ProfileError] = ProfileError) -> Node:
    """Parse a YAML file into a ``Node``; every problem carries the file and a line."""
    return from_bytes(read_bytes(path, error), str(path), error)


def from_bytes(data: bytes, name: str, error: type[ProfileError] = ProfileError) -> Node:
    """The root ``Node`` of the file ``name`` that held ``data`` (``load`` once the bytes
    are read: for a reader that keeps them)."""
    return Node(parse(data, name, error), name, "", error)


def read_bytes(path: Path, error: type[ProfileError] = ProfileError) -> bytes:
    """A whole small file (at most ``MAX_BYTES``), or ``error``."""
    try:
        with path.open("rb") as fh:
            data = fh.read(MAX_BYTES + 1)
    except OSError as exc:
        raise error(f"cannot read: {exc.strerror or exc}", file=str(path)) from None
    if len(data) > MAX_BYTES:
        raise error(f"the file is larger than {MAX_BYTES >> 10} KiB; not read",
                    file=str(path), line=1)
    return data


def utf8(data: bytes, name: str, error: type[ProfileError] = ProfileError) -> str:
    """UTF-8 text, or ``error`` at the line of the first byte that is not."""
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise error(f"not UTF-8 text (byte 0x{data[exc.start]:02X})", file=name,
                    line=data.count(b"\n", 0, exc.start) + 1) from None


def parse(data: bytes, name: str, error: type[ProfileError] = ProfileError) -> yaml.Node:
    """Bytes -> the composed root node, within the bounds above, or ``error`` with a line."""
    text = utf8(data, name, error)
    try:
        if _depth_bound(text) > _C_SAFE_DEPTH:
            _check_depth(text, name, error)
        root = yaml.compose(text, Loader=_COMPOSER)
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        line = mark.line + 1 if mark else 1
        raise error(f"YAML syntax: {exc.problem or exc.context}", file=name, line=line) from None
    except yaml.reader.ReaderError as exc:  # libyaml: a byte offset into the UTF-8 text
        raise error(f"YAML: character 0x{exc.character:02X} is not allowed"
                    if isinstance(exc.character, int) else f"YAML: {exc.reason}", file=name,
                    line=data.count(b"\n", 0, max(exc.position, 0)) + 1) from None
    except yaml.YAMLError as exc:
        raise error(f"YAML: {exc}".splitlines()[0], file=name, line=1) from None
    if root is None:
        raise error("the file is empty", file=name, line=1)
    if "<<" in text or _ANCHOR_OR_TAG.search(text):  # else no node is shared: the size
        _check_size(root, name, error)  # cap bounds the work, and the walk costs ms
    return root


# an anchor (&name) or a tag (!x) where a token may start: without one, no alias or merge
# can expand and nothing needs the walk
_ANCHOR_OR_TAG = re.compile(r"(?:^|[\s\[{,])[&!]", re.MULTILINE)


def _depth_bound(text: str) -> int:
    """More than the file's nesting can be, cheaply: each flow level needs a bracket (and
    may hold a one-pair mapping), each block level a column or two of indentation."""
    longest = max(map(len, text.splitlines()), default=0)
    return 2 * (text.count("[") + text.count("{") + longest + 1)


_OPEN = (yaml.FlowSequenceStartToken, yaml.FlowMappingStartToken,
         yaml.BlockSequenceStartToken, yaml.BlockMappingStartToken)
_CLOSE = (yaml.FlowSequenceEndToken, yaml.FlowMappingEndToken, yaml.BlockEndToken)


def _check_depth(text: str, name: str, error: type[ProfileError]) -> None:
    """Scan tokens (lazily: the scan stops at the first level too deep) for the nesting."""
    depth = 0
    for token in yaml.scan(text, Loader=_COMPOSER):
        if isinstance(token, _OPEN):
            depth += 1
            if depth > MAX_DEPTH:
                raise error(f"nested more than {MAX_DEPTH} levels deep", file=name,
                            line=token.start_mark.line + 1)
        elif isinstance(token, _CLOSE):
            depth -= 1


def _check_size(root: yaml.Node, name: str, error: type[ProfileError]) -> None:
    """Count the nodes as walking them would see them, every alias and merge expanded.

    Memoised per node, so counting is linear in the file even when its expansion is
    exponential (nested merge keys, "billion laughs"); a node that contains itself is
    refused, as is a ``<<`` whose value is not a mapping or a list of mappings.
    """
    size: dict[int, int] = {}
    depth: dict[int, int] = {}
    active: set[int] = set()
    stack: list[tuple[yaml.Node, list[yaml.Node] | None]] = [(root, None)]
    while stack:
        node, children = stack.pop()
        key = id(node)
        if children is not None:  # its children are done
            active.discard(key)
            total, deepest = 1, 0
            for c in children:
                if c.__class__ is yaml.ScalarNode:
                    total, deepest = total + 1, max(deepest, 1)
                else:
                    total, deepest = total + size[id(c)], max(deepest, depth[id(c)])
            size[key], depth[key] = total, deepest + 1
            if size[key] > MAX_NODES:
                raise error(f"more than {MAX_NODES} values once aliases and merge keys are "
                            f"expanded", file=name, line=node.start_mark.line + 1)
            if depth[key] > MAX_DEPTH + 1:
                raise error(f"nested more than {MAX_DEPTH} levels deep", file=name,
                            line=node.start_mark.line + 1)
            continue
        if key in size:
            continue
        if key in active:
            raise error("an alias refers to a node that contains it", file=name,
                        line=node.start_mark.line + 1)
        active.add(key)
        children = _children(node, name, error)
        stack.append((node, children))
        stack.extend((c, None) for c in children
                     if c.__class__ is not yaml.ScalarNode and id(c) not in size)


def _children(node: yaml.Node, name: str, error: type[ProfileError]) -> list[yaml.Node]:
    if isinstance(node, yaml.SequenceNode):
        return list(node.value)
    if not isinstance(node, yaml.MappingNode):
        return []
    out: list[yaml.Node] = []
    for knode, vnode in node.value:
        if knode.tag != _MERGE:
            out += (knode, vnode)
            continue
        merged = vnode.value if isinstance(vnode, yaml.SequenceNode) else [vnode]
        for m in merged:
            if not isinstance(m, yaml.MappingNode):
                raise error("a merge key (<<) takes a mapping or a list of mappings",
                            file=name, line=m.start_mark.line + 1)
        out += merged
    return out
