"""Settings: the configuration fields users set, each described once, where it is defined.

A configuration dataclass marks each field a user may set with `setting(default, description,
...)`: the field's metadata then holds a `Setting` (description, valid range or choices, the
parameter's name where it differs from the field's, whether it may change while running).
Fields without one are internal. meshfg_ros.parameters derives the parameters of the nodes and
of the replay, and the configurations made from parameter values, from these fields; the
estimator reads `dynamic_fields` to know what `SlidingWindowEstimator.reconfigure` may change.

`checked_value` is the one validator of a setting's value: the configurations check their
fields with it (`check_settings`), and meshfg_ros.parameters checks and converts parameter
values with it, so a value means and fails the same way in code, in a parameters file and on
the command line.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = [
    "SETTING_TYPES",
    "Setting",
    "bound_text",
    "check_settings",
    "checked_value",
    "dynamic_fields",
    "setting",
    "setting_type",
    "settings_of",
]

_METADATA_KEY = "meshfg_setting"
# The types of a setting's value: ROS parameter type names (rcl_interfaces/ParameterType without
# the PARAMETER_ prefix), since every setting is a parameter.
SETTING_TYPES = ("double", "integer", "string", "bool", "double_array", "integer_array")
_PYTHON_TYPES = ((bool, "bool"), (int, "integer"), (float, "double"), (str, "string"))


@dataclass(frozen=True)
class Setting:
    """How users see one configuration field.

    description: what the field does, in sentences ending with a full stop. range: inclusive
    (low, high) of the value (of each element of an array); either bound may be None
    (unbounded). choices: the allowed strings. parameter: the parameter's name (None: the
    field's). type: one of SETTING_TYPES (None: the default value's type, `setting_type`).
    length: the required length of an array. dynamic: may change while running; otherwise it is
    read once at start-up.
    """

    description: str
    range: tuple[float | None, float | None] | None = None
    choices: tuple[str, ...] | None = None
    parameter: str | None = None
    type: str | None = None
    length: int | None = None
    dynamic: bool = False


def setting(default: Any, description: str, **options: Any) -> Any:
    """A dataclass field with `default` that users set, described by `description` and `options`
    (the other fields of Setting). A setting of several configurations is declared once, on a
    configuration they inherit."""
    return dataclasses.field(default=default, metadata={_METADATA_KEY: Setting(description, **options)})


def settings_of(config_class: type) -> tuple[tuple[str, Any, Setting], ...]:
    """(field name, default, Setting) of each field of `config_class` that users set, in field order."""
    return tuple((item.name, item.default, item.metadata[_METADATA_KEY])
                 for item in dataclasses.fields(config_class) if _METADATA_KEY in item.metadata)


def dynamic_fields(config_class: type) -> frozenset[str]:
    """Names of the fields of `config_class` that may change while running."""
    return frozenset(name for name, _, spec in settings_of(config_class) if spec.dynamic)


def setting_type(name: str, default: Any, declared: str | None = None) -> str:
    """The type (SETTING_TYPES) of the setting `name`: `declared` (Setting.type), else its
    default's (a tuple: an array of its first element's type)."""
    if declared is not None:
        return declared
    if isinstance(default, tuple) and default:
        return f"{setting_type(name, default[0])}_array"
    for python_type, type_name in _PYTHON_TYPES:
        if isinstance(default, python_type):
            return type_name
    raise TypeError(f"{name}: give the setting type of default {default!r}")


def checked_value(name: str, value: Any, kind: str, range: tuple[float | None, float | None] | None = None,
                  choices: tuple[str, ...] | None = None, length: int | None = None,
                  error: type[Exception] = ValueError) -> Any:
    """`value` of the setting `name`, of type `kind` (SETTING_TYPES), converted to its canonical
    Python type (float, int, str, bool, a tuple of them), or `error` naming the setting (an
    array's element by its index): a bool, a string among `choices`, an integer, a finite number
    (an integer is accepted for a double) within the inclusive `range`, an array of `length`
    such elements."""
    if kind.endswith("_array"):
        if isinstance(value, (str, bytes, Mapping)) or not hasattr(value, "__iter__"):
            raise error(f"{name} must be a list, got {value!r}")
        items = list(value)
        if length is not None and len(items) != length:
            raise error(f"{name} must have {length} values, got {len(items)}")
        element_kind = kind.removesuffix("_array")
        return tuple(_checked_scalar(f"{name}[{index}]", item, element_kind, range, choices, error)
                     for index, item in enumerate(items))
    return _checked_scalar(name, value, kind, range, choices, error)


def _checked_scalar(label: str, value: Any, kind: str, range, choices, error: type[Exception]) -> Any:
    if kind == "bool":
        if not isinstance(value, (bool, np.bool_)):
            raise error(f"{label} must be a bool, got {value!r}")
        return bool(value)
    if kind == "string":
        if not isinstance(value, str):
            raise error(f"{label} must be a string, got {value!r}")
        if choices is not None and value not in choices:
            raise error(f"{label} must be one of {', '.join(choices)}; got {value!r}")
        return value
    is_integer = isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))
    if kind == "integer":
        if not is_integer:
            raise error(f"{label} must be an integer, got {value!r}")
        number = int(value)
    else:
        if not (is_integer or isinstance(value, (float, np.floating))):
            raise error(f"{label} must be a number, got {value!r}")
        number = float(value)
        if not math.isfinite(number):
            raise error(f"{label} must be finite, got {value!r}")
    if range is not None:
        low, high = range
        if (low is not None and number < low) or (high is not None and number > high):
            raise error(f"{label} = {number} is outside [{bound_text(low, '-inf')}, {bound_text(high, 'inf')}]")
    return number


def bound_text(value: float | None, unbounded: str) -> str:
    """A range's bound as users read it: `unbounded` for None."""
    return unbounded if value is None else f"{value:g}"


def check_settings(config: Any, error: type[Exception] = ValueError) -> None:
    """Check each set field of the dataclass instance `config` with `checked_value` against its
    Setting. None passes (a field whose None means "not set"). Raises `error` naming the field."""
    for name, default, spec in settings_of(type(config)):
        value = getattr(config, name)
        if value is not None:
            checked_value(name, value, setting_type(name, default, spec.type), spec.range, spec.choices,
                          spec.length, error)
