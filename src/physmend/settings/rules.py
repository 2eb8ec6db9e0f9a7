"""The rules of settings, checked by pydantic, and said in words.

A settings class is a frozen pydantic dataclass (:data:`STRICT`: no unknown key); each field's type
is its rule, built from the kinds below with bounds from :mod:`annotated_types` (``Annotated[Whole,
Ge(1)]``: a whole number ≥ 1) or a ``Literal`` of the words it may be. The same type says the rule in
words (:func:`rule_of`), so a :class:`SettingError` names the key, the rule and the value as given
(``train.epochs must be a whole number ≥ 1, but got 0``).

Text that reads as a number (``"1e-5"``) is that number; a whole number may be given as ``2.0``, not
``2.5``; ``true``/``false`` are never numbers, nor numbers switches.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import types
from collections.abc import Mapping
from typing import Annotated, Any, ClassVar, Literal, Union, get_args, get_origin

from annotated_types import Ge, Gt, Le
from omegaconf import OmegaConf
from pydantic import AllowInfNan, BeforeValidator, ConfigDict, Strict, TypeAdapter, ValidationError

from physmend.settings.shipped import SettingError, shipped_default, shipped_group

AUTO = "auto"

#: every settings class's pydantic configuration: a key it does not know is an error
STRICT = ConfigDict(extra="forbid")


@dataclasses.dataclass(frozen=True)
class Kind:
    """What a setting holds, for its rule in words (``int``, ``float``, ``word``, ``list``, ``auto``,
    ``names``, ``switch``, ``any``, or ``words`` given as they are)."""

    name: str
    words: str = ""


def _number(value: Any) -> Any:
    """Text that reads as a number is that number (a bool is no number: left for the type to refuse)."""
    if isinstance(value, str):
        try:
            return float(value)
        except ValueError:
            return value
    return value


def _whole(value: Any) -> Any:
    value = _number(value)
    return int(value) if isinstance(value, float) and value.is_integer() else value


def _real(value: Any) -> Any:
    value = _number(value)
    return float(value) if isinstance(value, int) and not isinstance(value, bool) else value


def _auto(value: Any) -> Any:
    return AUTO if value is None or value == AUTO else _real(value)


def _auto_whole(value: Any) -> Any:
    return AUTO if value is None or value == AUTO else _whole(value)


def _tuple(value: Any) -> Any:
    return tuple(value) if isinstance(value, list) else value


#: a whole number (``2.0`` and ``"2"`` too, not ``2.5`` nor ``true``)
Whole = Annotated[int, BeforeValidator(_whole), Strict(), Kind("int")]
#: a finite number
Number = Annotated[float, BeforeValidator(_real), Strict(), AllowInfNan(False), Kind("float")]
#: ``auto`` (or null) or a finite number > 0
Auto = Annotated[Union[Literal["auto"], Annotated[float, Strict(), AllowInfNan(False), Gt(0)]],
                 BeforeValidator(_auto), Kind("auto")]
#: ``auto`` (or null) or a whole number ≥ 1 (a count of processes)
AutoCount = Annotated[Union[Literal["auto"], Annotated[int, Strict(), Ge(1)]], BeforeValidator(_auto_whole),
                      Kind("word", words="'auto' or a whole number ≥ 1")]
#: a word (text)
Word = Annotated[str, Strict(), Kind("word")]
#: true or false
Flag = Annotated[bool, Strict(), Kind("bool")]
#: a list of names or glob patterns (a tuple once checked)
Patterns = Annotated[tuple[Any, ...], BeforeValidator(_tuple), Kind("list")]
#: ``auto`` (text: checked where it is used) or a list of names/patterns
Names = Annotated[Union[Annotated[str, Strict()], tuple[Any, ...], None], BeforeValidator(_tuple), Kind("names")]
#: true, false or a list of names/patterns
Switch = Annotated[Union[Annotated[bool, Strict()], tuple[Any, ...], None], BeforeValidator(_tuple), Kind("switch")]
#: anything (checked where it is used: solver and back-end options, per-equation choices)
Free = Annotated[Any, Kind("any")]


@dataclasses.dataclass(frozen=True)
class Rule:
    """A setting's rule as its type says it: ``kind`` (of :class:`Kind`), inclusive bounds ``low`` and
    ``high`` (``above``: ``> low``), the words it may be (``choices``), and whether null is allowed
    (the shipped YAML says what null means; messages state the rule of a value)."""

    kind: str
    low: float = -math.inf
    high: float = math.inf
    above: bool = False
    choices: tuple[Any, ...] = ()
    optional: bool = False
    words: str = ""

    def text(self) -> str:
        """The rule in words, as messages state it (``a whole number ≥ 1``, ``a number in (0, 1]``)."""
        return self._text()

    def _text(self) -> str:
        if self.words:
            return self.words
        fixed = {"bool": "true or false", "word": "a word", "list": "a list of names/patterns",
                 "names": "'auto' or a list of names/patterns", "auto": "'auto' or a number > 0",
                 "switch": "true, false or a list of names/patterns", "any": "anything"}
        if self.choices:
            return f"one of {list(self.choices)}"
        if self.kind in fixed:
            return fixed[self.kind]
        what = "a whole number" if self.kind == "int" else "a number"
        opening = "(" if self.above else "["
        if self.low == -math.inf:
            return f"{what} ≤ {self.high:g}" if self.high < math.inf else f"a finite {what[2:]}"
        if self.high == math.inf:
            return f"{what} {'>' if self.above else '≥'} {self.low:g}"
        return f"{what} in {opening}{self.low:g}, {self.high:g}]"


def _describe(hint: Any, meta: tuple[Any, ...] = ()) -> Rule:
    """The :class:`Rule` a field's type ``hint`` (with its ``Annotated`` metadata ``meta``) states."""
    if get_origin(hint) is Annotated:
        base, *more = get_args(hint)
        return _describe(base, (*meta, *more))
    kind = next((m for m in meta if isinstance(m, Kind)), None)
    if kind is None and get_origin(hint) in (Union, types.UnionType) and type(None) in get_args(hint):
        other = next(a for a in get_args(hint) if a is not type(None))
        return dataclasses.replace(_describe(other, meta), optional=True)
    if kind is None and get_origin(hint) is Literal:
        return Rule("word", choices=get_args(hint))
    if kind is None:
        return Rule("group" if isinstance(hint, type) and issubclass(hint, Group) else "any")
    rule = Rule(kind.name, words=kind.words)
    for m in meta:
        if isinstance(m, Ge):
            rule = dataclasses.replace(rule, low=float(m.ge))
        elif isinstance(m, Gt):
            rule = dataclasses.replace(rule, low=float(m.gt), above=True)
        elif isinstance(m, Le):
            rule = dataclasses.replace(rule, high=float(m.le))
    return rule


def _field_type(cls: type, key: str) -> Any:
    return cls.__pydantic_fields__[key].rebuild_annotation()  # type: ignore[attr-defined]


@functools.lru_cache(maxsize=None)
def rule_of(cls: type, key: str) -> Rule | None:
    """The rule of field ``key`` of settings class ``cls`` (None: not one of its keys)."""
    if key not in getattr(cls, "__pydantic_fields__", {}):
        return None
    return _describe(_field_type(cls, key))


@functools.lru_cache(maxsize=None)
def _adapter(cls: type, key: str) -> TypeAdapter[Any]:
    return TypeAdapter(_field_type(cls, key))


def check_field(cls: type, key: str, value: Any, name: str) -> Any:
    """``value`` of field ``key`` of settings class ``cls`` checked by its rule; returns it (a number
    where text reads as one, a list as a tuple). Raises :class:`SettingError` naming ``name``."""
    try:
        return _adapter(cls, key).validate_python(value)
    except ValidationError:
        raise SettingError(f"{name} must be {rule_of(cls, key).text()}, but got {value!r}") from None  # type: ignore[union-attr]


def plain(node: Any) -> dict[str, Any]:
    """``node`` (a DictConfig, a mapping or a settings object) as a dict of its keys."""
    if node is None:
        return {}
    if OmegaConf.is_config(node):
        return OmegaConf.to_container(node, resolve=True)  # type: ignore[return-value]
    if isinstance(node, Mapping):
        return dict(node)
    if dataclasses.is_dataclass(node):
        return {f.name: getattr(node, f.name) for f in dataclasses.fields(node)}
    raise SettingError(f"settings must be a mapping of keys to values, but got {type(node).__name__}")


@functools.lru_cache(maxsize=None)
def _names(cls: type) -> tuple[str, ...]:
    return tuple(f.name for f in dataclasses.fields(cls))


@functools.lru_cache(maxsize=None)
def _groups(cls: type) -> dict[str, type[Group]]:
    """The fields of ``cls`` that are settings classes themselves (``ude.inputs``), by name."""
    return {name: cls.__pydantic_fields__[name].annotation for name in _names(cls)  # type: ignore[attr-defined]
            if rule_of(cls, name).kind == "group"}  # type: ignore[union-attr]


class Group:
    """Building a settings class from a configuration group (a mapping), checked; ``GROUP``: its name
    (``""``: the top-level keys of ``conf/config.yaml``)."""

    GROUP: ClassVar[str]

    @classmethod
    def build(cls, node: Any, prefix: str | None = None) -> Any:
        """The settings of ``node`` (a DictConfig, a mapping, or already these settings); a missing key
        gets its shipped default, an unknown key or a value against its rule is a :class:`SettingError`."""
        if isinstance(node, cls):
            return node
        prefix = cls.GROUP if prefix is None else prefix
        dot = f"{prefix}." if prefix else ""
        raw = plain(node)
        cls.check_keys(raw, prefix)
        groups = _groups(cls)
        values: dict[str, Any] = {}
        for name in _names(cls):
            key = f"{dot}{name}"
            value = raw[name] if name in raw else cls.default(key.split(".", 1)[1] if cls.GROUP else key)
            values[name] = groups[name].build(value, key) if name in groups else value
        try:
            return cls(**values)
        except ValidationError as exc:
            name = str(exc.errors()[0]["loc"][0])
            raise SettingError(f"{dot}{name} must be {rule_of(cls, name).text()}, "  # type: ignore[union-attr]
                               f"but got {values[name]!r}") from None

    @classmethod
    def check_keys(cls, keys: Any, prefix: str) -> None:
        """Raise :class:`SettingError` naming the first of ``keys`` that is not a field (``prefix``: the group as shown)."""
        unknown = sorted(set(keys) - set(_names(cls)))
        if unknown:
            dot = f"{prefix}." if prefix else ""
            raise SettingError(f"{dot}{unknown[0]} is not a setting of {prefix or 'the configuration'}; "
                               f"the settings are: {', '.join(_names(cls))}")

    @classmethod
    def check(cls, key: str, value: Any, name: str | None = None) -> Any:
        """``value`` of this group's ``key`` checked by its rule (:func:`check_field`); ``name``: the key
        as messages show it (default ``<group>.<key>``)."""
        return check_field(cls, key, value, name or (f"{cls.GROUP}.{key}" if cls.GROUP else key))

    @classmethod
    def default(cls, key: str) -> Any:
        """The shipped default of ``key`` (dotted below the group); one that interpolates a top-level key
        (``sweep.seed: ${seed}``) is that key's shipped value."""
        value = shipped_default(cls.GROUP, key) if cls.GROUP else shipped_group("")[key]
        if isinstance(value, str) and "${" in value:
            value = OmegaConf.create({**shipped_group(""), "value": value}).value
        return value
