"""Home Assistant's YAML tags, followed the way Home Assistant follows them.

A Home Assistant configuration is rarely one file: ``sensors: !include sdm630.yaml``,
``!include_dir_merge_list modbus/``, ``port: !secret modbus_port``. Home Assistant
resolves every path relative to the file that names it; ``!include_dir_*`` take the
``*.yaml`` files below a folder (sorted, hidden folders and ``secrets.yaml`` left out);
``!secret NAME`` looks in ``secrets.yaml`` beside the file, then in each folder above it
up to the configuration's own; ``!env_var NAME [DEFAULT]`` reads the environment.

Each resolved node keeps its own file and line, so a note about an included sensor
names the included file. Secret values are returned to the caller, never put into a
message. Bounded: at most ``MAX_FILES`` files and ``MAX_DEPTH`` nested includes.

A configuration from a forum or a customer is untrusted: every file it includes must be
in the configuration's own folder or below it, symbolic links resolved (``!include
/etc/shadow``, ``../../secrets.yaml`` or a link out of the folder is a ``file:line``
error naming the tag, and the file is never opened).
"""

from __future__ import annotations

import os
from pathlib import Path

from rtupoll.config.yamlsrc import Node, load
from rtupoll.errors import ConfigError

MAX_FILES = 256
MAX_DEPTH = 16
SECRETS = "secrets.yaml"
_DIR_LISTS = ("!include_dir_list", "!include_dir_merge_list")
_DIR_MAPS = ("!include_dir_named", "!include_dir_merge_named")


def tag(node: Node) -> str:
    return str(node.node.tag)


class HaYaml:
    """One configuration and everything it includes."""

    def __init__(self, path: Path) -> None:
        self.root = load(path, ConfigError)
        self.top = path.parent.resolve()
        self._files = 1
        self._secrets: dict[Path, dict[str, Node] | None] = {}

    # -- following tags ------------------------------------------------------
    def resolve(self, node: Node) -> Node:
        """The node itself, or what a chain of ``!include FILE`` leads to."""
        for _ in range(MAX_DEPTH):
            if tag(node) != "!include":
                return node
            node = self._load(node, self._target(node))
        raise node.fail(f"more than {MAX_DEPTH} nested !include")

    def is_list(self, node: Node) -> bool:
        return tag(node) in _DIR_LISTS or self.resolve(node).is_list

    def sequence(self, node: Node) -> list[Node]:
        t = tag(node)
        if t == "!include_dir_list":
            return [self.resolve(n) for n in self._folder(node)]
        if t == "!include_dir_merge_list":
            return [self.resolve(item) for n in self._folder(node)
                    for item in self.sequence(n)]
        return [self.resolve(n) for n in self.resolve(node).sequence()]

    def mapping(self, node: Node) -> dict[str, Node]:
        t = tag(node)
        if t == "!include_dir_named":
            return {Path(n.file).stem: self.resolve(n) for n in self._folder(node)}
        if t == "!include_dir_merge_named":
            out: dict[str, Node] = {}
            for n in self._folder(node):
                out.update(self.mapping(n))
            return out
        if t in _DIR_LISTS:
            raise node.fail(f"expected a mapping, got {t}")
        return {k: self.resolve(v) for k, v in self.resolve(node).mapping().items()}

    def text(self, node: Node) -> str:
        t = tag(node)
        if t == "!secret":
            return self._secret(node)
        if t == "!env_var":
            name, _, default = str(node.node.value).strip().partition(" ")
            value = os.environ.get(name, default.strip() or None)
            if value is None:
                raise node.fail(f"!env_var {name}: not set, and no default given")
            return value
        return self.resolve(node).text()

    # -- files ---------------------------------------------------------------
    def _target(self, node: Node) -> Path:
        if not isinstance(node.node.value, str) or not node.node.value.strip():
            raise node.fail(f"{tag(node)} needs a file or folder name")
        path = Path(node.file).parent / node.node.value.strip()
        self._confined(node, path)
        return path

    def _confined(self, at: Node, path: Path, *, of_folder: bool = False) -> None:
        """Refuse ``path`` outside the configuration's folder (links resolved)."""
        what = f"{tag(at)} {at.node.value}: " + (f"{path.name} " if of_folder else "")
        try:
            real = path.resolve()
        except (OSError, RuntimeError):  # a link loop
            raise at.fail(f"{what}cannot be resolved") from None
        if real != self.top and self.top not in real.parents:
            raise at.fail(f"{what}{'links ' if of_folder else ''}outside the configuration's "
                          f"folder ({self.top}); only files in it and below it are read")

    def _load(self, at: Node, path: Path) -> Node:
        self._confined(at, path, of_folder=tag(at) != "!include")  # (a link out of it)
        if not path.is_file():
            raise at.fail(f"{tag(at)} {at.node.value}: no such file ({path})")
        self._files += 1
        if self._files > MAX_FILES:
            raise at.fail(f"more than {MAX_FILES} included files")
        return load(path, ConfigError)

    def _folder(self, node: Node) -> list[Node]:
        folder = self._target(node)
        if not folder.is_dir():
            raise node.fail(f"{tag(node)} {node.node.value}: no such folder ({folder})")
        files = []
        for here, dirs, names in os.walk(folder):
            dirs[:] = sorted(d for d in dirs if not d.startswith("."))
            files += [Path(here) / n for n in sorted(names)
                      if n.endswith(".yaml") and n != SECRETS and not n.startswith(".")]
        return [self._load(node, f) for f in files]

    def _secret(self, node: Node) -> str:
        name = str(node.node.value).strip()
        here = Path(node.file).parent.resolve()
        while True:
            secrets = self._secrets_in(here, node)
            if secrets is not None and name in secrets:
                return self.text(secrets[name])
            if here == self.top or here.parent == here or self.top not in here.parents:
                break
            here = here.parent
        raise node.fail(f"!secret {name}: not found in {SECRETS} beside the file "
                        f"or above it")

    def _secrets_in(self, folder: Path, at: Node) -> dict[str, Node] | None:
        if folder not in self._secrets:
            path = folder / SECRETS
            if path.is_file():
                self._confined(at, path, of_folder=True)
            self._secrets[folder] = load(path, ConfigError).mapping() if path.is_file() \
                else None
        return self._secrets[folder]
