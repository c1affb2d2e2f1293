"""``randt config`` and the settings defaults ``--help`` shows, read from the pydantic models themselves.

:data:`GROUPS` names the settings models behind the commands. Every field of each is a row (its
default, its environment variable if the model is a pydantic-settings one, its description); a
field whose type is itself a model (say the service's ``matcher``) is a group of its own, so a
group nested later shows up without touching this module. Models are imported only when printed.
"""

from __future__ import annotations

import dataclasses
import importlib
import json
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Annotated, Any

import typer
from typer.core import TyperCommand

__all__ = ["GROUPS", "SettingRow", "SettingsGroup", "settings_command", "settings_groups", "show_config"]

#: The groups ``randt config`` prints, in order: group name -> ``module:Class`` (a pydantic model,
#: a pydantic-settings model or a dataclass).
GROUPS: dict[str, str] = {
    "registration": "randt.core.config:RegistrationSettings",  # randt register (--method, --voxel)
    "matcher": "randt.core.odometry:MatcherSettings",  # the incremental matcher: randt map, the service
    "service": "randt.service.settings:ServiceSettings",  # randt serve
    "publisher": "randt.clients.publisher:PublisherSettings",  # randt replay, randt simulate, vehicles
    "fleet": "randt.clients.fleet:FleetSettings",  # randt simulate's flags
}


@dataclass(frozen=True)
class SettingRow:
    """One field: its name, default (JSON-ready), environment variable (or None) and description."""

    name: str
    default: Any
    env: str | None
    help: str


@dataclass(frozen=True)
class SettingsGroup:
    """One settings model: where it is defined, a note on its environment, its fields."""

    name: str
    source: str
    env_note: str
    rows: tuple[SettingRow, ...]


def _load(path: str) -> type:
    module, _, name = path.partition(":")
    return getattr(importlib.import_module(module), name)


def _jsonable(value: Any) -> Any:
    from pydantic_core import to_jsonable_python

    return to_jsonable_python(value)


def _is_model(tp: Any) -> bool:
    from pydantic import BaseModel

    return isinstance(tp, type) and issubclass(tp, BaseModel)


def _env_config(model: type) -> tuple[str | None, str | None]:
    """``(env_prefix, env_nested_delimiter)`` of a pydantic-settings model; ``(None, None)`` otherwise."""
    from pydantic_settings import BaseSettings

    if not (isinstance(model, type) and issubclass(model, BaseSettings)):
        return None, None
    return model.model_config.get("env_prefix", "") or "", model.model_config.get("env_nested_delimiter")


def _fields(model: type) -> list[tuple[str, Any, Any, str, str | None]]:
    """``(name, type, default, description, alias)`` of each field of a pydantic model or dataclass."""
    if _is_model(model):
        out = []
        for name, info in model.model_fields.items():  # type: ignore[attr-defined]
            default = info.get_default(call_default_factory=True)
            alias = info.validation_alias if isinstance(info.validation_alias, str) else None
            out.append((name, info.annotation, default, info.description or "", alias))
        return out
    if dataclasses.is_dataclass(model):
        out = []
        for f in dataclasses.fields(model):
            if f.default is not dataclasses.MISSING:
                default = f.default
            elif f.default_factory is not dataclasses.MISSING:
                default = f.default_factory()
            else:
                default = None
            out.append((f.name, f.type, default, "", None))
        return out
    raise TypeError(f"{model!r} is neither a pydantic model nor a dataclass")


def settings_groups(groups: Mapping[str, type | str] | None = None) -> list[SettingsGroup]:
    """The groups of ``groups`` (default :data:`GROUPS`) and of the models nested in them.

    A nested model is its own group, named after its field (``parent.field`` if that name is
    taken), placed right after its parent, with the defaults the parent gives it (the service's
    ``registration`` starts from the matcher's defaults, not pairwise registration's). A model
    listed at the top level and also nested with the same defaults is shown once, where it is
    nested (with the environment variables that reach it there).
    """
    models = {name: _load(m) if isinstance(m, str) else m for name, m in (groups or GROUPS).items()}

    def same_defaults(tp: type, default: Any) -> bool:
        return _jsonable(default) == _jsonable(tp())

    nested_types = {
        tp
        for model in models.values()
        for _, tp, default, _, _ in _fields(model)
        if _is_model(tp) and same_defaults(tp, default)
    }
    taken = {name for name, model in models.items() if model not in nested_types}
    out: list[SettingsGroup] = []

    def add(
        name: str, model: type, env_prefix: str | None, delimiter: str | None, note: str, instance: Any = None
    ) -> None:
        rows, children = [], []
        for field, tp, default, text, alias in _fields(model):
            if instance is not None:
                default = getattr(instance, field)
            env = alias.upper() if alias and env_prefix is not None else None
            if env is None and env_prefix is not None:
                env = f"{env_prefix}{field}".upper()
            if _is_model(tp):
                children.append((field, tp, env, default))
                continue
            rows.append(SettingRow(field, _jsonable(default), env, text))
        source = f"{model.__module__}.{model.__qualname__}"
        out.append(SettingsGroup(name, source, note, tuple(rows)))
        for field, tp, env, default in children:
            child = field if field not in taken else f"{name}.{field}"
            taken.add(child)
            if env is None:
                add(child, tp, None, None, "", default)
            elif delimiter:
                add(child, tp, f"{env}{delimiter}", delimiter, f"env prefix {env}{delimiter}", default)
            else:
                add(child, tp, None, None, f"env {env} (the whole group as JSON)", default)

    for name, model in models.items():
        if model in nested_types:
            continue
        prefix, delimiter = _env_config(model)
        add(name, model, prefix, delimiter, f"env prefix {prefix}" if prefix is not None else "no env vars")
    return out


def _text(value: Any) -> str:
    return value if isinstance(value, str) else json.dumps(value)


def show_config(
    as_json: Annotated[
        bool, typer.Option("--json", help="Print one JSON object: group -> defaults, env, source.")
    ] = False,
) -> None:
    """Print every settings group: each setting's default, environment variable and meaning."""
    groups = settings_groups()
    if as_json:
        doc = {
            g.name: {
                "source": g.source,
                "defaults": {r.name: r.default for r in g.rows},
                "env": {r.name: r.env for r in g.rows if r.env},
            }
            for g in groups
        }
        typer.echo(json.dumps(doc, indent=1))
        return
    for k, g in enumerate(groups):
        typer.echo(f"{'' if k == 0 else chr(10)}[{g.name}]  {g.source}; {g.env_note}")
        width = max(len(r.name) for r in g.rows)
        dwidth = max(len(_text(r.default)) for r in g.rows)
        ewidth = max(len(r.env or "-") for r in g.rows)
        for r in g.rows:
            line = f"{r.name:<{width}}  {_text(r.default):<{dwidth}}  {r.env or '-':<{ewidth}}  {r.help}"
            typer.echo(line.rstrip())


def describe_setting(model: type, field: str) -> str:
    """``default: ...; env var: ...`` of one field (``randt serve --help`` and the vehicle commands)."""
    group = next(g for g in settings_groups({"_": model}) if g.name == "_")
    row = next(r for r in group.rows if r.name == field)
    value = row.default
    if value is None:
        shown = "(none)"
    else:
        shown = (", ".join(map(str, value)) or "(none)") if isinstance(value, list) else _text(value)
    parts = [f"default: {shown}"]
    if row.env:
        parts.append(f"env var: {row.env}" + (" (a JSON list)" if isinstance(value, list) else ""))
    return "; ".join(parts)


def settings_command(model: str, options: tuple[str, ...]) -> type[TyperCommand]:
    """A command class whose ``--help`` shows, for each of ``options``, the default and environment
    variable of the ``model`` field of the same name (the option itself defaults to None: unset,
    the settings' environment and defaults apply). The model is imported only to render help."""

    class SettingsHelpCommand(TyperCommand):
        def format_help(self, ctx: Any, formatter: Any) -> None:
            if not getattr(self, "_settings_described", False):
                cls = _load(model)
                for param in self.params:
                    if param.name in options:
                        described = describe_setting(cls, param.name)
                        param.help = f"{param.help}  [{described}]"  # type: ignore[attr-defined]
                self._settings_described = True
            super().format_help(ctx, formatter)

    return SettingsHelpCommand
