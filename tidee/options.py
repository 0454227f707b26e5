"""The dataclass is the command line: each option is declared once, as a typed config field.

A command's options are the fields of one config dataclass (nested config dataclasses are
flattened into the same flags). The flag, its type, its choices, its default and its help all
come from the field::

    @dataclass
    class SoakConfig:
        sessions: int = option(1000, "sessions opened and closed, one after another", type=positive_int)
        renderer: Renderer = option("tiny", "who draws the frames")      # Literal: choices

    add_options(parser, SoakConfig)          # --sessions, --renderer {auto,egl,tiny}
    cfg = from_args(SoakConfig, args)        # a SoakConfig, nested configs rebuilt
    to_argv(cfg)                             # ["--sessions", "20"]: only what differs from default

Why a small helper over ``dataclasses.fields`` and argparse rather than a generator library
(tyro, simple-parsing): the command line keeps argparse's one-line errors and this project's
``type=`` validators (``tidee.argtypes``), the flag names users and docs already use stay
exactly as they are, parsing imports nothing heavy (``tidee --help`` must not load torch),
and the whole mechanism is this one readable file.

Inference from the annotation: ``int``/``float``/``str``/``Path``; ``X | None`` (the default
may be None); ``bool`` (False: ``--flag``; True: ``--flag/--no-flag``); ``Literal[...]`` and
``Enum`` (choices); ``tuple[X, ...]`` (a comma list, or ``nargs="+"`` when asked). Anything
else needs ``type=``. A field without a default is a required flag.
"""

from __future__ import annotations

import argparse
import dataclasses
import enum
import functools
import types
import typing
from collections.abc import Callable, Collection, Iterator, Sequence
from pathlib import Path
from typing import Any, TypeVar

T = TypeVar("T")

_KEY = "tidee.option"


@dataclasses.dataclass(frozen=True)
class OptionSpec:
    """How one field appears on the command line (kept in the field's metadata)."""

    help: str = ""
    flag: str | None = None  # default: --field-name
    type: Callable[[str], Any] | None = None  # parse one value (default: from the annotation)
    choices: Collection[Any] | None = None  # default: a Literal's or an Enum's values; live views work
    metavar: str | None = None
    nargs: str | None = None  # "+": several values after one flag (tuple fields)
    repeat: bool = False  # tuple fields: the flag once per value (--report a --report b); required
    cli: bool = True  # False: a config field the command line does not set


def option(
    default: Any = dataclasses.MISSING,
    help: str = "",
    *,
    flag: str | None = None,
    type: Callable[[str], Any] | None = None,
    choices: Collection[Any] | None = None,
    metavar: str | None = None,
    nargs: str | None = None,
    repeat: bool = False,
    default_factory: Callable[[], Any] | Any = dataclasses.MISSING,
    cli: bool = True,
) -> Any:
    """A dataclass field that is also a command-line option (see the module docstring)."""
    spec = OptionSpec(
        help=help, flag=flag, type=type, choices=choices, metavar=metavar, nargs=nargs, repeat=repeat, cli=cli
    )
    if default_factory is not dataclasses.MISSING:
        return dataclasses.field(default_factory=default_factory, metadata={_KEY: spec})
    if isinstance(default, list | dict | set):
        raise TypeError("a mutable default needs default_factory=")
    return dataclasses.field(default=default, metadata={_KEY: spec})


def spec_of(f: dataclasses.Field) -> OptionSpec:
    return f.metadata.get(_KEY) or OptionSpec()


def flag_of(f: dataclasses.Field) -> str:
    return spec_of(f).flag or "--" + f.name.replace("_", "-")


def dest_of(f: dataclasses.Field) -> str:
    return flag_of(f).lstrip("-").replace("-", "_")


@dataclasses.dataclass(frozen=True)
class Leaf:
    """One flag: the field it comes from, the path of nested fields to it and its default."""

    path: tuple[str, ...]  # field names from the command's config down to this field
    field: dataclasses.Field
    hint: Any  # the resolved annotation
    default: Any  # dataclasses.MISSING: required

    @property
    def flag(self) -> str:
        return flag_of(self.field)

    @property
    def dest(self) -> str:
        return dest_of(self.field)


def _hints(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def _is_config(hint: Any) -> bool:
    return isinstance(hint, type) and dataclasses.is_dataclass(hint)


def _field_default(f: dataclasses.Field) -> Any:
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return dataclasses.MISSING


def nested_defaults(f: dataclasses.Field) -> dict[str, Any]:
    """The defaults a parent gives a nested config field beyond its class's own.

    ``option(default_factory=Cls)``: none. ``option(default_factory=functools.partial(Cls, seed=200))``:
    ``{"seed": 200}``. Declared this way, not read from a built instance, so that what a config
    computes in ``__post_init__`` (e.g. an "auto" resolved) never becomes a command-line default.
    """
    factory = f.default_factory
    if isinstance(factory, functools.partial):
        return dict(factory.keywords)
    if factory is dataclasses.MISSING or isinstance(factory, type):
        return {}
    raise TypeError(
        f"nested config field {f.name!r}: give default_factory=Cls or functools.partial(Cls, **defaults)"
    )


def leaves(cls: type, overrides: dict[str, Any] | None = None, path: tuple[str, ...] = ()) -> Iterator[Leaf]:
    """Every command-line field of ``cls``, nested configs flattened, in declaration order.

    ``overrides``: defaults that differ from the class's (see :func:`nested_defaults`).
    """
    hints = _hints(cls)
    overrides = overrides or {}
    for f in dataclasses.fields(cls):
        spec = spec_of(f)
        if not spec.cli or not f.init:
            continue
        hint = hints[f.name]
        if _is_config(hint):
            yield from leaves(hint, nested_defaults(f), (*path, f.name))
        else:
            yield Leaf((*path, f.name), f, hint, overrides.get(f.name, _field_default(f)))


def _strip_optional(hint: Any) -> tuple[Any, bool]:
    origin = typing.get_origin(hint)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(hint) if a is not type(None)]
        if len(args) == 1:
            return args[0], True
    return hint, False


def _scalar(hint: Any) -> tuple[Callable[[str], Any], Sequence[Any] | None]:
    """(parse one value, choices) for a scalar annotation."""
    if typing.get_origin(hint) is typing.Literal:
        values = typing.get_args(hint)
        return type(values[0]), values
    if isinstance(hint, type) and issubclass(hint, enum.Enum):
        return hint, [m for m in hint]
    if hint in (int, float, str):
        return hint, None
    if hint is Path:
        return Path, None
    raise TypeError(f"no command-line parser for {hint!r}: give the option type=")


def _comma_list(parse: Callable[[str], Any], choices: Collection[Any] | None) -> Callable[[str], tuple]:
    def parse_list(text: str) -> tuple:
        items = tuple(parse(item.strip()) for item in text.split(",") if item.strip())
        if choices is not None:
            bad = [i for i in items if i not in choices]
            if bad:
                raise argparse.ArgumentTypeError(
                    f"{', '.join(map(str, bad))} not among {', '.join(map(str, choices))}"
                )
        return items

    parse_list.__name__ = "comma list"
    return parse_list


def _show(value: Any) -> str:
    if isinstance(value, enum.Enum):
        return str(value.value)
    if isinstance(value, tuple | list):
        return ",".join(_show(v) for v in value)
    return str(value)


def add_options(
    parser: argparse.ArgumentParser,
    cls: type,
    *,
    skip: Sequence[str] = (),
    exclusive: Sequence[Sequence[str]] = (),
) -> None:
    """Add a flag for every command-line field of ``cls``.

    ``skip``: fields to leave out (a name, or a dotted path into nested configs). ``exclusive``:
    groups of field names at most one of which a command line may give (argparse refuses the
    line in one sentence). The parser remembers which config its flags came from
    (``configs_of``), so ``from_args`` and the tests can find it again.
    """
    registered: list[tuple[type, tuple[str, ...]]] = getattr(parser, "_tidee_configs", [])
    registered.append((cls, tuple(skip)))
    parser._tidee_configs = registered  # type: ignore[attr-defined]
    groups: dict[str, Any] = {}
    for names in exclusive:
        group = parser.add_mutually_exclusive_group()
        groups.update(dict.fromkeys(names, group))
    for leaf in leaves(cls):
        if leaf.path[-1] in skip or ".".join(leaf.path) in skip:
            continue
        target = groups.get(".".join(leaf.path)) or groups.get(leaf.path[-1]) or parser
        target.add_argument(leaf.flag, **_argument(leaf))


def _validator(parse: Callable[[str], Any]) -> Callable[[str], Any]:
    """``parse`` with its ValueError turned into argparse's refusal, message kept (argparse would
    otherwise print only "invalid value"). Validators stay free of argparse."""

    def checked(text: str) -> Any:
        try:
            return parse(text)
        except ValueError as e:
            raise argparse.ArgumentTypeError(str(e)) from None

    checked.__name__ = getattr(parse, "__name__", "value")
    return checked


def _argument(leaf: Leaf) -> dict[str, Any]:
    spec = spec_of(leaf.field)
    hint, _optional = _strip_optional(leaf.hint)
    kw: dict[str, Any] = {"dest": leaf.dest, "help": spec.help or None}
    if spec.metavar:
        kw["metavar"] = spec.metavar
    if leaf.default is dataclasses.MISSING:
        kw["required"] = True
    else:
        kw["default"] = leaf.default
    if hint is bool:
        if leaf.default is True:
            kw["action"] = argparse.BooleanOptionalAction
        else:
            kw["action"] = "store_true"
        return kw
    origin = typing.get_origin(hint)
    if origin is tuple:
        args = typing.get_args(hint)
        inner = args[0]
        parse, choices = (_validator(spec.type), spec.choices) if spec.type else _scalar(inner)
        choices = spec.choices or choices
        if spec.repeat:
            if leaf.default is not dataclasses.MISSING:
                raise TypeError(f"{leaf.flag}: a repeated flag must be required (no default)")
            kw.update(action="append", type=parse)
        elif spec.nargs:
            kw.update(nargs=spec.nargs, type=parse)
            if choices:
                kw["choices"] = choices
        else:
            kw["type"] = _comma_list(parse, choices)
            kw.setdefault(
                "metavar", "A,B,..." if not choices else "{" + ",".join(map(_show, choices)) + "},..."
            )
    else:
        parse, choices = (_validator(spec.type), spec.choices) if spec.type else _scalar(hint)
        kw["type"] = parse
        if spec.choices or choices:
            kw["choices"] = spec.choices or choices
    if leaf.default not in (dataclasses.MISSING, None, "") and "default" not in (spec.help or ""):
        kw["help"] = (spec.help + " " if spec.help else "") + f"(default: {_show(leaf.default)})"
    return kw


def configs_of(parser: argparse.ArgumentParser) -> list[tuple[type, tuple[str, ...]]]:
    """The configs whose fields ``add_options`` turned into this parser's flags."""
    return list(getattr(parser, "_tidee_configs", []))


def from_args(cls: type[T], args: argparse.Namespace, **overrides: Any) -> T:
    """An instance of ``cls`` from parsed flags; fields without a flag keep their defaults.

    ``overrides`` (field names of ``cls``) win over the flags.
    """
    return _build(cls, args, {}, overrides)


def _build(cls: type, args: argparse.Namespace, defaults: dict[str, Any], overrides: dict[str, Any]) -> Any:
    hints = _hints(cls)
    kwargs: dict[str, Any] = {}
    for f in dataclasses.fields(cls):
        if not f.init:
            continue
        if f.name in overrides:
            kwargs[f.name] = overrides[f.name]
            continue
        spec = spec_of(f)
        if _is_config(hints[f.name]) and spec.cli:
            kwargs[f.name] = _build(hints[f.name], args, nested_defaults(f), {})
        elif spec.cli and hasattr(args, dest_of(f)):
            got = getattr(args, dest_of(f))
            if isinstance(got, list):  # nargs="+" and repeated flags give a list
                got = tuple(got)
            elif isinstance(got, str) and _strip_optional(hints[f.name])[0] is Path:
                got = Path(got)  # a validator (argtypes.output_path) checked the text
            kwargs[f.name] = got
        elif f.name in defaults:
            kwargs[f.name] = defaults[f.name]
        elif _field_default(f) is not dataclasses.MISSING:
            kwargs[f.name] = _field_default(f)
    return cls(**kwargs)


def to_argv(config: Any, *, skip: Sequence[str] = ()) -> list[str]:
    """The flags that rebuild ``config`` through ``from_args`` (only those that differ from the
    defaults), e.g. to start a child process with the same options."""
    out: list[str] = []
    values = dict(_values(config))
    for leaf in leaves(type(config)):
        if leaf.path[-1] in skip or ".".join(leaf.path) in skip:
            continue
        value = values[leaf.path]
        if leaf.default is not dataclasses.MISSING and value == leaf.default:
            continue
        hint, _ = _strip_optional(leaf.hint)
        if hint is bool:
            out.append(leaf.flag if value else "--no-" + leaf.flag[2:])
        elif value is None:
            continue
        elif isinstance(value, tuple | list) and spec_of(leaf.field).repeat:
            out += [item for v in value for item in (leaf.flag, _show(v))]
        elif isinstance(value, tuple | list) and spec_of(leaf.field).nargs:
            out += [leaf.flag, *(_show(v) for v in value)]
        else:
            out += [leaf.flag, _show(value)]
    return out


def _values(config: Any, path: tuple[str, ...] = ()) -> Iterator[tuple[tuple[str, ...], Any]]:
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            yield from _values(value, (*path, f.name))
        else:
            yield (*path, f.name), value


def add_command(
    group: argparse._SubParsersAction,
    name: str,
    cls: type[T],
    run: Callable[[T], int],
    help: str,
    *,
    skip: Sequence[str] = (),
    exclusive: Sequence[Sequence[str]] = (),
) -> argparse.ArgumentParser:
    """A subcommand whose flags are ``cls``'s fields and which calls ``run(config)``.

    ``run`` should import what it needs inside itself: building the parser then stays cheap.
    """
    parser = group.add_parser(name, help=help, description=help)
    add_options(parser, cls, skip=skip, exclusive=exclusive)
    parser.set_defaults(func=lambda args: run(from_args(cls, args)))
    return parser
