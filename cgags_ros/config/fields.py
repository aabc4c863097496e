"""
Typed, documented config fields: the one declaration every layer's options come from.

Each config field is declared with :func:`option`, which records a description, the
allowed range or choices, whether it is an advanced (research) switch and whether it is a
ROS parameter of the node (read-only or not) in the field metadata. A field's dotted path
(``pairing.mode``, ``core.gravity``) is its one name: in YAML, ``--set``, the Python API
and, for ``ros=True`` fields, as the ROS parameter. From that single declaration come
validation (:func:`validate`), flattening (:func:`flatten`, :func:`update_from_flat`), the
generated parameter file and docs (:mod:`cgags_ros.config.files`) and the ROS parameter
descriptors (:mod:`cgags_ros.ros.parameters`). Pure Python: the core may import it.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Mapping, Sequence

from ..errors import InvalidConfigError


def option(default: Any, description: str, *, low: float | None = None,
           high: float | None = None, choices: tuple | None = None,
           allow_none: bool = False, advanced: bool = False, ros: bool = False,
           read_only: bool = False) -> Any:
    """
    Declare a dataclass field with a description and a valid range or set of choices.

    ``low``/``high`` are inclusive. A tuple default declares a vector of that many finite
    numbers (a YAML or ROS array). ``advanced`` marks a research switch: still settable
    everywhere, documented in docs/parameters.md, never a ROS parameter. ``ros`` makes the
    key a ROS parameter of the node; ``read_only`` fixes it once the node runs.
    """
    if advanced and ros:
        raise ValueError('a research switch (advanced) is never a ROS parameter')
    meta = {'description': description, 'low': low, 'high': high, 'choices': choices,
            'allow_none': allow_none, 'advanced': advanced, 'ros': ros, 'read_only': read_only}
    return dataclasses.field(default=default, metadata=meta)


def section(cls: type) -> Any:
    """Declare a nested section: its fields' keys are ``<section>.<field>``."""
    return dataclasses.field(default_factory=cls)


def check_vector(name: str, default: tuple, value: Any) -> tuple:
    """Return ``value`` as a tuple of ``len(default)`` finite floats, or raise."""
    items = value.tolist() if hasattr(value, 'tolist') else value
    if (isinstance(items, (str, bytes, Mapping)) or not hasattr(items, '__len__')
            or len(items) != len(default)
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool)
                       and math.isfinite(v) for v in items)):
        raise InvalidConfigError(f'{name} must be a list of {len(default)} finite numbers, '
                                 f'got {value!r}')
    return tuple(float(v) for v in items)


def _check_field(owner: str, f: dataclasses.Field, value: Any) -> Any:
    meta = f.metadata
    name = f'{owner}{f.name}'
    if value is None:
        if meta.get('allow_none'):
            return None
        raise InvalidConfigError(f'{name} must not be None')
    default = f.default
    if isinstance(default, tuple):
        return check_vector(name, default, value)
    if isinstance(default, bool) or (default is None and isinstance(value, bool)):
        if not isinstance(value, bool):
            raise InvalidConfigError(f'{name} must be true or false, got {value!r}')
        return value
    if isinstance(default, int) and not isinstance(default, bool):
        if (isinstance(value, bool) or not isinstance(value, (int, float))
                or float(value) != int(value)):
            raise InvalidConfigError(f'{name} must be an integer, got {value!r}')
        value = int(value)
    elif isinstance(default, float) or (default is None and isinstance(value, (int, float))):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise InvalidConfigError(f'{name} must be a number, got {value!r}')
        value = float(value)
        if not math.isfinite(value):
            raise InvalidConfigError(f'{name} must be finite, got {value!r}')
    elif isinstance(default, str):
        if not isinstance(value, str):
            raise InvalidConfigError(f'{name} must be a string, got {value!r}')
    low, high, choices = meta.get('low'), meta.get('high'), meta.get('choices')
    if low is not None and value < low:
        raise InvalidConfigError(f'{name} = {value!r} is below its minimum {low}')
    if high is not None and value > high:
        raise InvalidConfigError(f'{name} = {value!r} is above its maximum {high}')
    if choices is not None and value not in choices:
        allowed = ', '.join(map(str, choices))
        raise InvalidConfigError(f'{name} = {value!r} is not one of {allowed}')
    return value


def validate(cfg: Any, _prefix: str = '') -> Any:
    """Check (and coerce ints/floats of) every field in place; raise InvalidConfigError."""
    for f in dataclasses.fields(cfg):
        value = getattr(cfg, f.name)
        if dataclasses.is_dataclass(value):
            validate(value, f'{_prefix}{f.name}.')
        else:
            setattr(cfg, f.name, _check_field(_prefix, f, value))
    post = getattr(cfg, 'check', None)
    if callable(post):
        post()
    return cfg


def flatten(cfg: Any, _prefix: str = '') -> dict[str, Any]:
    """``{'core.p1': 0.99, 'voxel_size': 0.05, ...}`` for YAML and ROS params."""
    out: dict[str, Any] = {}
    for f in dataclasses.fields(cfg):
        value = getattr(cfg, f.name)
        if dataclasses.is_dataclass(value):
            out.update(flatten(value, f'{_prefix}{f.name}.'))
        else:
            out[f'{_prefix}{f.name}'] = value
    return out


def describe(cls_or_cfg: Any, _prefix: str = '') -> dict[str, dict[str, Any]]:
    """
    Return the flattened field metadata of a config class or instance.

    The result is ``{key: {description, low, high, choices, advanced, default}}``.
    """
    cfg = cls_or_cfg() if isinstance(cls_or_cfg, type) else cls_or_cfg
    out: dict[str, dict[str, Any]] = {}
    for f in dataclasses.fields(cfg):
        value = getattr(cfg, f.name)
        if dataclasses.is_dataclass(value):
            out.update(describe(value, f'{_prefix}{f.name}.'))
        else:
            out[f'{_prefix}{f.name}'] = dict(f.metadata, default=value)
    return out


def update_from_flat(cfg: Any, values: Mapping[str, Any]) -> Any:
    """
    Return a validated copy of ``cfg`` with flat keys (or nested dicts) applied.

    Unknown keys raise InvalidConfigError naming the key, so a typo never passes silently.
    """
    new = _deepcopy(cfg)
    for key, value in flatten_mapping(values).items():
        target = new
        parts = key.split('.')
        for part in parts[:-1]:
            if not hasattr(target, part) or not dataclasses.is_dataclass(getattr(target, part)):
                raise InvalidConfigError(f'unknown configuration key {key!r}')
            target = getattr(target, part)
        names = {f.name for f in dataclasses.fields(target)}
        if parts[-1] not in names or dataclasses.is_dataclass(getattr(target, parts[-1])):
            raise InvalidConfigError(f'unknown configuration key {key!r}')
        setattr(target, parts[-1], value)
    return validate(new)


def flatten_mapping(values: Mapping[str, Any], prefix: str = '') -> dict[str, Any]:
    """Nested mapping -> flat ``a.b.c`` keys (the inverse layout of a YAML section)."""
    out: dict[str, Any] = {}
    for key, value in values.items():
        if isinstance(value, Mapping):
            out.update(flatten_mapping(value, f'{prefix}{key}.'))
        else:
            out[f'{prefix}{key}'] = value
    return out


def _deepcopy(cfg: Any) -> Any:
    changes = {f.name: _deepcopy(getattr(cfg, f.name))
               for f in dataclasses.fields(cfg) if dataclasses.is_dataclass(getattr(cfg, f.name))}
    return dataclasses.replace(cfg, **changes)


def parse_key_values(items: Sequence[str]) -> dict[str, Any]:
    """
    Parse command-line overrides into a dict with YAML-typed values.

    ``['core.p1=0.9', 'refine.method=gicp']`` becomes ``{'core.p1': 0.9, 'refine.method':
    'gicp'}`` (3 -> int, true -> bool). Raises InvalidConfigError on a bad item.
    """
    import yaml

    out: dict[str, Any] = {}
    for item in items:
        key, sep, raw = item.partition('=')
        if not sep or not key.strip():
            raise InvalidConfigError(f'--set expects KEY=VALUE, got {item!r}')
        try:
            out[key.strip()] = yaml.safe_load(raw)
        except yaml.YAMLError as exc:
            raise InvalidConfigError(f'--set {item!r}: value is not valid YAML ({exc})') from exc
    return out
