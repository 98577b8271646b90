"""``@frozen`` is ``@dataclass(frozen=True)`` with its methods written on first use: the
same behaviour, nothing compiled at import (rtupoll/frozen.py)."""

from __future__ import annotations

import dataclasses
import pickle
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest

from rtupoll.frozen import frozen, mutable


def _default_tags() -> list[str]:
    return ["a"]


@frozen
class Lazy:
    name: str
    size: int = 2
    tags: list[str] = field(default_factory=_default_tags)
    note: str = field(default="", compare=False, repr=False)

    def double(self) -> int:
        return self.size * 2


@dataclass(frozen=True)
class Eager:
    name: str
    size: int = 2
    tags: list[str] = field(default_factory=_default_tags)
    note: str = field(default="", compare=False, repr=False)


@frozen
class LazyChild(Lazy):
    extra: float = 0.5


@frozen
class Checked:
    low: int
    high: int

    def __post_init__(self) -> None:
        if self.low > self.high:
            raise ValueError("low above high")


def test_made_the_same_way_as_a_frozen_dataclass() -> None:
    lazy, eager = Lazy("x", 3, note="n"), Eager("x", 3, note="n")
    assert repr(lazy) == repr(eager).replace("Eager", "Lazy")
    assert repr(lazy) == "Lazy(name='x', size=3, tags=['a'])"
    assert (lazy.name, lazy.size, lazy.tags, lazy.note, lazy.double()) == ("x", 3, ["a"], "n", 6)
    assert Lazy(name="x", size=3) == lazy and Lazy("x", 3, note="other") == lazy  # compare=False
    assert Lazy("x") != lazy and Lazy("x", 3) != Eager("x", 3)  # another class is never equal
    assert Lazy("x").tags is not Lazy("x").tags  # each gets its own from the factory
    assert [f.name for f in dataclasses.fields(Lazy)] == ["name", "size", "tags", "note"]
    assert Lazy.__match_args__ == Eager.__match_args__ == ("name", "size", "tags", "note")
    assert dataclasses.is_dataclass(lazy)
    assert dataclasses.asdict(lazy) == {"name": "x", "size": 3, "tags": ["a"], "note": "n"}


def test_hash_follows_the_compared_fields() -> None:
    a, b = Checked(1, 2), Checked(1, 2)
    assert hash(a) == hash(b) and len({a, b, Checked(2, 3)}) == 2
    with pytest.raises(TypeError, match="unhashable"):
        hash(Lazy("x"))  # a list field: unhashable, as the dataclass's own hash says


@pytest.mark.parametrize("cls", [Lazy, Eager])
def test_wrong_arguments_are_the_same_errors(cls: Any) -> None:
    with pytest.raises(TypeError, match="missing 1 required positional argument: 'name'"):
        cls()
    with pytest.raises(TypeError, match="unexpected keyword argument 'colour'"):
        cls("x", colour=1)
    with pytest.raises(TypeError, match="takes from 2 to 5 positional arguments but 6"):
        cls("x", 1, [], "", 9)


@pytest.mark.parametrize("cls", [Lazy, Eager])
def test_assigning_or_deleting_a_field_is_refused(cls: Any) -> None:
    item = cls("x")
    with pytest.raises(dataclasses.FrozenInstanceError, match="cannot assign to field 'size'"):
        item.size = 4
    with pytest.raises(dataclasses.FrozenInstanceError, match="cannot delete field 'name'"):
        del item.name
    with pytest.raises(dataclasses.FrozenInstanceError):
        item.other = 1  # not a field either: frozen means frozen


def test_replace_pickle_post_init_and_a_subclass() -> None:
    item = Lazy("x", 3)
    assert dataclasses.replace(item, size=5) == Lazy("x", 5)
    assert pickle.loads(pickle.dumps(item)) == item
    with pytest.raises(ValueError, match="low above high"):
        Checked(3, 1)
    child = LazyChild("y", extra=1.5)
    assert repr(child) == "LazyChild(name='y', size=2, tags=['a'], extra=1.5)"
    assert child != Lazy("y") and child == LazyChild("y", 2, ["a"], "", 1.5)
    with pytest.raises(dataclasses.FrozenInstanceError):
        child.extra = 2.0


def test_an_unpickled_object_works_before_any_was_made() -> None:
    # the profile cache's way: the object comes back without __init__ ever running
    script = ("import pickle, sys; sys.path.insert(0, sys.argv[1]); import test_frozen as t; "
              "item = pickle.loads(bytes.fromhex(sys.argv[2])); "
              "print(item, item == t.Lazy('x', 3), hash(t.Checked(1, 2)) == hash(t.Checked(1, 2)))")
    out = subprocess.run([sys.executable, "-c", script, str(Path(__file__).parent),
                          pickle.dumps(Lazy("x", 3)).hex()], capture_output=True, text=True,
                         check=True, timeout=60).stdout
    assert out == "Lazy(name='x', size=3, tags=['a']) True True\n"


def test_methods_of_its_own_are_refused() -> None:
    with pytest.raises(TypeError, match="defines a method @frozen makes"):
        @frozen
        class Own:
            a: int

            def __repr__(self) -> str:
                return "own"


def test_importing_the_profile_model_compiles_almost_nothing() -> None:
    """What @frozen is for: the model's classes cost nothing to declare. Only the classes
    made at import (the function table's, the profile's default sections) write their
    __init__; with @dataclass(frozen=True) the same import compiled 96 methods."""
    script = """if True:
        import builtins, sys
        made = []
        real = builtins.exec
        def counting(*args, **kwargs):
            if sys._getframe(1).f_code.co_filename.endswith("dataclasses.py"):
                made.append(1)
            return real(*args, **kwargs)
        builtins.exec = counting
        from rtupoll.model.profile import Choice, Field, Profile
        import rtupoll.config.library
        print(len(made) <= 7 * 3)
        methods = [getattr(c, m) for c in (Choice, Field, Profile)
                   for m in ("__init__", "__repr__", "__eq__", "__hash__")]
        print(all(m.__code__.co_filename.endswith("frozen.py") for m in methods))
        before = len(made)
        Choice("A") == Choice("A")
        print(len(made) > before)
    """
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                         check=True, timeout=60).stdout
    assert out == "True\nTrue\nTrue\n"


def test_a_class_without_a_docstring_is_documented_by_its_fields() -> None:
    # (dataclasses would ask inspect.signature: three quarters of a declaration's cost)
    assert Lazy.__doc__ == "Lazy(name, size, tags, note)"
    assert Checked.__doc__ == "Checked(low, high)"
    Checked(1, 2)
    assert Checked.__doc__ == "Checked(low, high)"  # still, once its methods are written


@frozen(slots=True)
class LazySlots:
    name: str
    size: int = 2
    tags: list[str] = field(default_factory=_default_tags)


@dataclass(frozen=True, slots=True)
class EagerSlots:
    name: str
    size: int = 2
    tags: list[str] = field(default_factory=_default_tags)


@mutable(slots=True)
class Plain:
    name: str
    size: int = 2
    tags: list[str] = field(default_factory=_default_tags)


@dataclass(slots=True)
class EagerPlain:
    name: str
    size: int = 2
    tags: list[str] = field(default_factory=_default_tags)


@mutable
class PlainDict:
    name: str
    size: int = 2


@pytest.mark.parametrize(("lazy", "eager"), [(LazySlots, EagerSlots), (Plain, EagerPlain)])
def test_slots_and_mutable_are_made_as_their_dataclass(lazy: Any, eager: Any) -> None:
    a, b = lazy("x", 3), eager("x", 3)
    assert repr(a) == repr(b).replace(eager.__name__, lazy.__name__)
    assert a == lazy("x", 3) and a != lazy("x") and a != b
    assert lazy.__slots__ == eager.__slots__ == ("name", "size", "tags")
    assert not hasattr(a, "__dict__")
    assert lazy.__match_args__ == eager.__match_args__
    assert dataclasses.replace(a, size=5) == lazy("x", 5)
    assert pickle.loads(pickle.dumps(a)) == a
    assert lazy("x").tags is not lazy("x").tags
    with pytest.raises(AttributeError):
        a.other = 1  # slots: no other attribute, as the dataclass
    with pytest.raises(TypeError, match="missing 1 required positional argument: 'name'"):
        lazy()


def test_a_frozen_class_with_slots_is_frozen_and_hashes() -> None:
    item = LazySlots("x")
    with pytest.raises(dataclasses.FrozenInstanceError, match="cannot assign to field 'size'"):
        item.size = 4
    with pytest.raises(TypeError, match="unhashable"):
        hash(item)  # a list field: unhashable, as the dataclass's own hash says
    assert hash(LazySlots("x", 3, ())) == hash(EagerSlots("x", 3, ()))  # type: ignore[arg-type]


@pytest.mark.parametrize("cls", [Plain, PlainDict, EagerPlain])
def test_a_mutable_class_assigns_and_does_not_hash(cls: Any) -> None:
    item = cls("x")
    item.size = 4
    assert item.size == 4 and item == cls("x", 4)
    assert cls.__hash__ is None
    with pytest.raises(TypeError, match="unhashable"):
        hash(item)
    assert repr(PlainDict("y")) == "PlainDict(name='y', size=2)"
