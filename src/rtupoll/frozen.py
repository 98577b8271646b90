"""``@frozen``: a frozen dataclass whose generated methods are made on first use.

``@dataclass(frozen=True)`` compiles six methods per class at import (``__init__``,
``__repr__``, ``__eq__``, ``__hash__``, ``__setattr__``, ``__delattr__``) and, for a
class with no docstring, asks ``inspect.signature`` for one: about 1 ms a class on
Python 3.11, and a one-shot read imported 40 such classes. ``@frozen`` declares the
same dataclass (its fields, ``dataclasses.fields``, ``replace``, ``asdict``, pickling,
``__match_args__``) without compiling anything (about 0.07 ms a class): the first call
of ``__init__`` or ``__repr__`` has the dataclass machinery write that method, the
first of ``__eq__`` or ``__hash__`` both, and from then on they are the very methods
``@dataclass(frozen=True)`` makes, at the same speed. A class whose instances only
come from the profile cache (unpickled, no ``__init__``) or are never made in a run
never pays. Assigning or deleting an attribute raises
``dataclasses.FrozenInstanceError`` as a frozen dataclass does. A class without a
docstring is documented as ``Name(field, ...)``.

For classes with plain fields (defaults, ``dataclasses.field(...)``), no options, no
methods of their own among those six; anything else (``ClassVar``, ``InitVar``,
``slots``, ``order``) stays ``@dataclass(frozen=True)``. A ``@frozen`` class is
subclassed only by ``@frozen`` classes.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any, TypeVar, dataclass_transform

T = TypeVar("T", bound=type)

_LAZY = ("__init__", "__repr__", "__eq__", "__hash__")


@dataclass_transform(frozen_default=True, field_specifiers=(dataclasses.field, dataclasses.Field))
def frozen(cls: T) -> T:
    """The frozen dataclass ``cls``, its methods written when first called."""
    if any(name in cls.__dict__ for name in (*_LAZY, "__setattr__", "__delattr__")):
        raise TypeError(f"{cls.__name__} defines a method @frozen makes")
    undocumented = not cls.__doc__
    if undocumented:  # else dataclasses documents it with inspect.signature: 3/4 of the cost
        cls.__doc__ = cls.__name__
    dataclasses.dataclass(cls, init=False, repr=False, eq=False)  # the fields: no code made
    every = cls.__dict__["__dataclass_fields__"]
    if undocumented:  # what dataclasses would say, without the types
        cls.__doc__ = f"{cls.__name__}({', '.join(every)})"
    if len(every) != len(dataclasses.fields(cls)):
        raise TypeError(f"{cls.__name__}: a ClassVar or InitVar needs @dataclass(frozen=True)")
    names = frozenset(every)
    for method in _LAZY:
        setattr(cls, method, _on_first_call(cls, method))

    def __setattr__(self: Any, name: str, value: Any) -> None:
        if type(self) is cls or name in names:
            raise dataclasses.FrozenInstanceError(f"cannot assign to field {name!r}")
        object.__setattr__(self, name, value)

    def __delattr__(self: Any, name: str) -> None:
        if type(self) is cls or name in names:
            raise dataclasses.FrozenInstanceError(f"cannot delete field {name!r}")
        object.__delattr__(self, name)

    for fn in (__setattr__, __delattr__):
        fn.__qualname__ = f"{cls.__qualname__}.{fn.__name__}"
        setattr(cls, fn.__name__, fn)
    return cls


def _on_first_call(cls: type, method: str) -> Callable[..., Any]:
    def first(self: Any, *args: Any, **kwargs: Any) -> Any:
        _write_method(cls, method)
        return getattr(cls, method)(self, *args, **kwargs)

    first.__qualname__ = f"{cls.__qualname__}.{method}"
    first.__name__ = method
    return first


# what each method takes of the dataclass machinery: __eq__ and __hash__ come together
# (``unsafe_hash`` writes the hash a frozen dataclass has, without __setattr__)
_OPTIONS = {"__init__": {"init": True, "repr": False, "eq": False, "frozen": True},
            "__repr__": {"init": False, "repr": True, "eq": False},
            "__eq__": {"init": False, "repr": False, "eq": True, "unsafe_hash": True}}
_OPTIONS["__hash__"] = _OPTIONS["__eq__"]


def _write_method(cls: type, method: str) -> None:
    """Give ``cls`` the ``method`` (with __eq__, __hash__ too) ``@dataclass(frozen=True)``
    writes for its fields: made on a twin class with the same fields (the ``Field``
    objects themselves), whose methods refer to nothing of the twin (``self.__class__``,
    the fields by name)."""
    fields = cls.__dict__["__dataclass_fields__"]
    namespace: dict[str, Any] = {
        "__annotations__": {name: f.type for name, f in fields.items()},
        "__module__": cls.__module__, "__qualname__": cls.__qualname__,
        "__doc__": cls.__doc__, **fields}
    if hasattr(cls, "__post_init__"):
        namespace["__post_init__"] = cls.__post_init__
    options = _OPTIONS[method]
    twin: type = dataclasses.dataclass(**options)(type(cls.__name__, (), namespace))
    for name in _LAZY:
        if _OPTIONS[name] is options:
            setattr(cls, name, twin.__dict__[name])
