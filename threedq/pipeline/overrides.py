"""Command-line overrides of a stage run, built from keyword arguments checked against what the stage takes.

:func:`stage_overrides` checks each model argument against the constructors of the stage class its configs name, each
data argument against the DataModule's, each trainer argument against :class:`lightning.pytorch.Trainer`'s.
"""

from __future__ import annotations

import importlib
import inspect
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import lightning as L
import yaml

from threedq.errors import InputError
from threedq.pipeline.lightning_cli import default_data, expand_configs

__all__ = ["class_of", "stage_overrides"]

_TRAINER_ARGUMENTS = frozenset(inspect.signature(L.Trainer.__init__).parameters) - {"self"}


def class_of(configs: Sequence[str | Path], key: str) -> type | None:
    """The class a run of ``configs`` builds for ``key`` (``"model"`` or ``"data"``): the last ``class_path`` the
    configs set (for ``data`` default: the CLI's default dataset); ``None`` when none sets one or it does not import."""
    path = default_data()["class_path"] if key == "data" else None
    for config in expand_configs(configs):
        doc = yaml.safe_load(Path(config).read_text()) or {}
        section = doc.get(key) if isinstance(doc, dict) else None
        if isinstance(section, dict) and isinstance(section.get("class_path"), str):
            path = section["class_path"]
    if path is None or "." not in path:
        return None
    module, name = path.rsplit(".", 1)
    try:
        return getattr(importlib.import_module(module), name)
    except (ImportError, AttributeError):
        return None


def _value(v: Any) -> str:
    if v is None:
        return "null"
    if isinstance(v, bool):
        return "true" if v else "false"
    return str(v)


def stage_overrides(configs: Sequence[str | Path], *, model: Mapping[str, Any] | None = None,
                    data: Mapping[str, Any] | None = None, trainer: Mapping[str, Any] | None = None) -> list[str]:
    """``--model.init_args.<k>=<v>``, ``--data.init_args.<k>=<v>`` and ``--trainer.<k>=<v>`` for a run of ``configs``.

    Args:
        configs: the stage's config files, in the order they are composed.
        model, data, trainer: the values to set (``None`` becomes ``null``, paths their text).

    Raises:
        InputError: a name the stage's model, its DataModule or the Trainer does not take (one line).
    """
    out: list[str] = []
    for key, values in (("model", model), ("data", data), ("trainer", trainer)):
        if not values:
            continue
        allowed = _TRAINER_ARGUMENTS if key == "trainer" else None
        if allowed is None:
            cls = class_of(configs, key)
            allowed = None if cls is None else _argument_names(cls)
            prefix = f"--{key}.init_args."
            owner = f"{cls.__name__} ({key} of {', '.join(Path(c).name for c in configs)})" if cls else key
        else:
            prefix, owner = "--trainer.", "lightning.Trainer"
        for name, v in values.items():
            if allowed is not None and name not in allowed:
                raise InputError(f"{owner}: takes no argument '{name}' (threedq em passes it: a renamed argument?)")
            out.append(f"{prefix}{name}={_value(v)}")
    return out


def _argument_names(cls: type) -> frozenset[str]:
    """Every named constructor argument of ``cls`` and its bases below Lightning's classes."""
    names: set[str] = set()
    for c in cls.__mro__:
        if c.__module__.startswith("lightning"):
            break
        init = c.__dict__.get("__init__")
        if init is not None:
            names |= {n for n, p in inspect.signature(init).parameters.items()
                      if n != "self" and p.kind not in (p.VAR_KEYWORD, p.VAR_POSITIONAL)}
    return frozenset(names)
