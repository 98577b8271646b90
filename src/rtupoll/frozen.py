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

``@frozen(slots=True)`` is ``@dataclass(frozen=True, slots=True)`` the same way (about
1 ms a class at import otherwise). ``@mutable`` and ``@mutable(slots=True)`` are
``@dataclass`` and ``@dataclass(slots=True)``: ``__init__``, ``__repr__`` and ``__eq__``
written on first use, ``__hash__`` None, as a dataclass that compares has.

For classes with plain fields (defaults, ``dataclasses.field(...)``), no options but
``slots``, no methods of their own among those six; anything else (``ClassVar``,
``InitVar``, ``order``, ``weakref_slot``) stays a ``@dataclass``. A ``@frozen`` class
is subclassed only by ``@frozen`` classes, a ``@mutable`` one only by ``@mutable``
ones.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any, TypeVar, cast, dataclass_transform, overload

T = TypeVar("T", bound=type)

_LAZY = ("__init__", "__repr__", "__eq__", "__hash__")
_MUTABLE_LAZY = ("__init__", "__repr__", "__eq__")


@overload
def frozen(cls: T, /) -> T: ...
@overload
def frozen(*, slots: bool = False) -> Callable[[T], T]: ...
@dataclass_transform(frozen_default=True, field_specifiers=(dataclasses.field, dataclasses.Field))
def frozen(cls: T | None = None, /, *, slots: bool = False) -> T | Callable[[T], T]:
    """The frozen dataclass ``cls``, its methods written when first called."""
    if cls is None:
        return lambda c: _declare(c, frozen=True, slots=slots)
    return _declare(cls, frozen=True, slots=slots)


@overload
def mutable(cls: T, /) -> T: ...
@overload
def mutable(*, slots: bool = False) -> Callable[[T], T]: ...
@dataclass_transform(field_specifiers=(dataclasses.field, dataclasses.Field))
def mutable(cls: T | None = None, /, *, slots: bool = False) -> T | Callable[[T], T]:
    """The (not frozen) dataclass ``cls``, its methods written when first called."""
    if cls is None:
        return lambda c: _declare(c, frozen=False, slots=slots)
    return _declare(cls, frozen=False, slots=slots)


def _declare(cls: T, *, frozen: bool, slots: bool) -> T:
    lazy = _LAZY if frozen else _MUTABLE_LAZY
    if any(name in cls.__dict__ for name in (*_LAZY, "__setattr__", "__delattr__")):
        raise TypeError(f"{cls.__name__} defines a method @{'frozen' if frozen else 'mutable'}"
                        " makes")
    undocumented = not cls.__doc__
    if undocumented:  # else dataclasses documents it with inspect.signature: 3/4 of the cost
        cls.__doc__ = cls.__name__
    # the fields (and the slots: a new class): no code made
    cls = cast(T, dataclasses.dataclass(cls, init=False, repr=False, eq=False, slots=slots))
    every = cls.__dict__["__dataclass_fields__"]
    if undocumented:  # what dataclasses would say, without the types
        cls.__doc__ = f"{cls.__name__}({', '.join(every)})"
    if len(every) != len(dataclasses.fields(cls)):
        raise TypeError(f"{cls.__name__}: a ClassVar or InitVar needs a @dataclass")
    options = _OPTIONS if frozen else _MUTABLE_OPTIONS
    for method in lazy:
        setattr(cls, method, _on_first_call(cls, method, options))
    if not frozen:
        cls.__hash__ = None  # type: ignore[assignment]  # as a dataclass with eq has
        return cls
    names = frozenset(every)

    def __setattr__(self: Any, name: str, value: Any) -> None:
        if type(self) is cls or name in names:
            raise dataclasses.FrozenInstanceError(f"cannot assign to field {name!r}")
        object.__setattr__(self, name, value)

    def __delattr__(self: Any, name: str) -> None:
        if type(self) is cls or name in names:
            raise dataclasses.FrozenInstanceError(f"cannot delete field {name!r}")
        object.__delattr__(self, name)

    def __getstate__(self: Any) -> list[Any]:  # what a frozen dataclass with slots pickles
        return [getattr(self, f.name) for f in dataclasses.fields(self)]

    def __setstate__(self: Any, state: list[Any]) -> None:
        for f, value in zip(dataclasses.fields(self), state, strict=False):
            object.__setattr__(self, f.name, value)

    own: tuple[Callable[..., Any], ...] = (__setattr__, __delattr__)
    if slots:
        own = (*own, __getstate__, __setstate__)
    for fn in own:
        fn.__qualname__ = f"{cls.__qualname__}.{fn.__name__}"
        setattr(cls, fn.__name__, fn)
    return cls


def _on_first_call(cls: type, method: str, options: dict[str, dict[str, bool]],
                   ) -> Callable[..., Any]:
    def first(self: Any, *args: Any, **kwargs: Any) -> Any:
        _write_method(cls, method, options)
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
_MUTABLE_OPTIONS = {"__init__": {"init": True, "repr": False, "eq": False},
                    "__repr__": _OPTIONS["__repr__"],
                    "__eq__": {"init": False, "repr": False, "eq": True}}


def _write_method(cls: type, method: str, table: dict[str, dict[str, bool]]) -> None:
    """Give ``cls`` the ``method`` (with __eq__, __hash__ too) the dataclass machinery
    writes for its fields: made on a twin class with the same fields (the ``Field``
    objects themselves), whose methods refer to nothing of the twin (``self.__class__``,
    the fields by name). An ``__init__`` of plain fields is written here instead, the
    same code as the dataclass's: a frozen twin would compile a ``__setattr__`` and a
    ``__delattr__`` only to throw them away (0.75 ms a class against 0.1)."""
    fields = cls.__dict__["__dataclass_fields__"]
    if method == "__init__":
        init = _plain_init(cls, fields, frozen=table is _OPTIONS)
        if init is not None:
            cls.__init__ = init  # type: ignore[misc]
            return
    namespace: dict[str, Any] = {
        "__annotations__": {name: f.type for name, f in fields.items()},
        "__module__": cls.__module__, "__qualname__": cls.__qualname__,
        "__doc__": cls.__doc__, **fields}
    if hasattr(cls, "__post_init__"):
        namespace["__post_init__"] = cls.__post_init__
    options = table[method]
    twin: type = dataclasses.dataclass(**options)(type(cls.__name__, (), namespace))
    for name in table:
        if table[name] is options and name in twin.__dict__:
            setattr(cls, name, twin.__dict__[name])


class _Factory:
    def __repr__(self) -> str:
        return "<factory>"


_FACTORY = _Factory()  # an argument not given whose default is made by a factory


def _plain_init(cls: type, fields: dict[str, dataclasses.Field[Any]], *, frozen: bool,
                ) -> Callable[..., None] | None:
    """The ``__init__`` dataclasses writes for ``fields`` when each is a plain init
    field (positional or keyword, a default or a factory or neither), or None (then the
    dataclass machinery writes it)."""
    params, body = [], []
    namespace: dict[str, Any] = {"__rtupoll_set": object.__setattr__,
                                 "__rtupoll_factory": _FACTORY}
    for i, f in enumerate(fields.values()):
        name = f.name
        if not f.init or f.kw_only is True or not name.isidentifier() or name == "self" \
                or name.startswith("__"):
            return None
        value = name
        if f.default is not dataclasses.MISSING:
            namespace[f"__rtupoll_d{i}"] = f.default
            params.append(f"{name}=__rtupoll_d{i}")
        elif f.default_factory is not dataclasses.MISSING:
            namespace[f"__rtupoll_f{i}"] = f.default_factory
            params.append(f"{name}=__rtupoll_factory")
            value = f"__rtupoll_f{i}() if {name} is __rtupoll_factory else {name}"
        else:
            params.append(name)
        body.append(f"__rtupoll_set(self, {name!r}, {value})" if frozen
                    else f"self.{name} = {value}")
    if hasattr(cls, "__post_init__"):
        body.append("self.__post_init__()")
    source = (f"def __init__(self, {', '.join(params)}):\n"
              + "".join(f"    {line}\n" for line in body or ["pass"]))
    try:
        exec(source, namespace)  # (the field names only: the values go in namespace)
    except SyntaxError:  # a field without a default after one with: the dataclass says so
        return None
    init: Callable[..., None] = namespace["__init__"]
    init.__qualname__ = f"{cls.__qualname__}.__init__"
    init.__annotations__ = {**{f.name: f.type for f in fields.values()}, "return": None}
    return init
