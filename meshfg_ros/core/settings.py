"""Settings: the configuration fields users set, each described once, where it is defined.

A configuration dataclass marks each field a user may set with `setting(default, description,
...)`: the field's metadata then holds a `Setting` (description, valid range or choices, the
parameter's name where it differs from the field's, whether it may change while running).
Fields without one are internal. meshfg_ros.parameters derives the parameters of the nodes and
of the replay, and the configurations made from parameter values, from these fields; the
estimator reads `dynamic_fields` to know what `SlidingWindowEstimator.reconfigure` may change.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from dataclasses import dataclass
from typing import Any

__all__ = ["Setting", "check_settings", "dynamic_fields", "setting", "settings_of"]

_METADATA_KEY = "meshfg_setting"


@dataclass(frozen=True)
class Setting:
    """How users see one configuration field.

    description: what the field does, in sentences ending with a full stop. range: inclusive
    (low, high) of the value (of each element of an array); either bound may be None
    (unbounded). choices: the allowed strings. parameter: the parameter's name (None: the
    field's). type: a parameter type name of meshfg_ros.parameters.PARAMETER_TYPES (None: the
    default value's type). length: the required length of an array. dynamic: may change while
    running; otherwise it is read once at start-up.
    """

    description: str
    range: tuple[float | None, float | None] | None = None
    choices: tuple[str, ...] | None = None
    parameter: str | None = None
    type: str | None = None
    length: int | None = None
    dynamic: bool = False


def setting(default: Any, description: str | Setting, **options: Any) -> Any:
    """A dataclass field with `default` that users set: described by `description` and `options`
    (the other fields of Setting), or by a Setting that several configurations share."""
    if isinstance(description, Setting):
        if options:
            raise TypeError("a shared Setting takes no further options")
        return dataclasses.field(default=default, metadata={_METADATA_KEY: description})
    return dataclasses.field(default=default, metadata={_METADATA_KEY: Setting(description, **options)})


def settings_of(config_class: type) -> tuple[tuple[str, Any, Setting], ...]:
    """(field name, default, Setting) of each field of `config_class` that users set, in field order."""
    return tuple((item.name, item.default, item.metadata[_METADATA_KEY])
                 for item in dataclasses.fields(config_class) if _METADATA_KEY in item.metadata)


def dynamic_fields(config_class: type) -> frozenset[str]:
    """Names of the fields of `config_class` that may change while running."""
    return frozenset(name for name, _, spec in settings_of(config_class) if spec.dynamic)


def check_settings(config: Any, error: type[Exception] = ValueError) -> None:
    """Check each set field of the dataclass instance `config` against its Setting: a string among
    the choices, an integer where the default is one, a number (each element of an array) finite
    and within the range. None passes (a field whose None means "not set"). Raises `error`
    naming the field."""
    for name, default, spec in settings_of(type(config)):
        value = getattr(config, name)
        if value is None:
            continue
        if _is_integer(default) and not _is_integer(value):
            raise error(f"{name} must be an integer, got {value!r}")
        if spec.choices is not None and value not in spec.choices:
            raise error(f"{name} must be one of {', '.join(spec.choices)}; got {value!r}")
        if spec.range is None:
            continue
        low, high = spec.range
        for item in value if isinstance(value, (tuple, list)) else (value,):
            if (isinstance(item, bool) or not isinstance(item, numbers.Real) or not math.isfinite(item)
                    or (low is not None and item < low) or (high is not None and item > high)):
                raise error(f"{name} must be finite and within [{low}, {high}], got {value!r}")


def _is_integer(value: Any) -> bool:
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)
