"""The one helper for argument checks at public boundaries.

Every public entry point validates its inputs through these functions so that a bad input
fails with a message that names it (docs/conventions.md, section 7).
"""
from __future__ import annotations

import functools
import re
import sys
from dataclasses import fields
from enum import Enum
from typing import Any, Callable, Iterable, Mapping, Sequence

import numpy as np
import torch

__all__ = ["InputError", "MIN_FRAME_SIZE", "check_frame_size", "check_number", "numeric_text_error", "one_line_errors", "check_shape", "check_finite", "check_finite_fast", "check_image_pair",
           "check_rotation", "check_same_size", "config_params", "option_params", "is_unset", "config_error", "Choice",
           "choice"]


class Choice(str, Enum):
    """A setting that is one of a few names: a schema field of such a type (its members' names are the values
    users type, ``flow.precision=int8``) makes OmegaConf refuse any other value when the config is composed or
    read (:func:`config_params`), so the code needs no check of its own. A member is its string: it compares,
    hashes, prints and serialises as its value."""

    __hash__ = str.__hash__

    def __str__(self) -> str:
        return str(self.value)

    def __format__(self, spec: str) -> str:
        return format(str(self.value), spec)

    @classmethod
    def _missing_(cls, value: object) -> "Choice | None":
        # A name of digits typed on the command line (data.previous=11) reaches OmegaConf as an int, which it
        # looks up by value: the member that number spells.
        if isinstance(value, int) and not isinstance(value, bool):
            return cls.__members__.get(str(value))
        return None


def choice(name: str, values: str, module: str) -> type[Choice]:
    """The :class:`Choice` ``name`` of the space-separated ``values``, each member named as its value (OmegaConf
    reads a value by its member's name). ``module``: the defining module's ``__name__``, where pickling (a
    batch's Ray tasks) finds the type."""
    return Choice(name, [(v, v) for v in values.split()], module=module)  # type: ignore[return-value]


class InputError(ValueError):
    """A public entry point was given an input it cannot use; the message names the input."""


#: Smallest frame ``(H, W)`` in pixels the pipeline solves. The binding limit is the flow pyramid:
#: OpenCV's DIS (8-pixel patches; also DeepFlow's matches) kills the process with a segmentation fault
#: on frames 12 rows high and fails on 16-24 px sides of wide frames (measured, OpenCV 5.1), while 32 px
#: sides pass at any aspect ratio. 32 px is also the FCN-8s stride (a smaller side would be a single,
#: mostly padded cell at its coarsest layer), and leaves at least 6 columns of ``w_s = 5`` px, 10 DP
#: cells of 3 rows and room for the 13 px window of the flow confidence's structure tensor.
MIN_FRAME_SIZE: tuple[int, int] = (32, 32)


def check_frame_size(height: int, width: int, name: str) -> None:
    """Fail unless a frame of ``height`` x ``width`` pixels is at least :data:`MIN_FRAME_SIZE`."""
    min_h, min_w = MIN_FRAME_SIZE
    if int(height) < min_h or int(width) < min_w:
        raise InputError(f"{name}: frame of {int(width)}x{int(height)} pixels (W x H) is smaller than the "
                         f"{min_w}x{min_h} the pipeline can solve (MIN_FRAME_SIZE: the flow pyramid needs it)")


def check_shape(x: torch.Tensor, shape: Sequence[int | str | None], name: str) -> None:
    """Check that ``x`` is a tensor of the given shape.

    Args:
        x: the tensor.
        shape: expected sizes; ``None`` or a string (a symbolic name such as ``"H"``) accepts any
            size, a string used twice must match itself. A leading ``"*"`` accepts any batch dims.
        name: the input's name for the message.
    """
    if not isinstance(x, torch.Tensor):
        raise InputError(f"{name}: expected a torch.Tensor, got {type(x).__name__}")
    shape = list(shape)
    dims = list(x.shape)
    if shape and shape[0] == "*":
        shape = shape[1:]
        if len(dims) < len(shape):
            raise InputError(f"{name}: expected shape (*, {_fmt(shape)}), got {tuple(dims)}")
        dims = dims[len(dims) - len(shape):]
    elif len(dims) != len(shape):
        raise InputError(f"{name}: expected shape ({_fmt(shape)}), got {tuple(x.shape)}")
    bound: dict[str, int] = {}
    for want, got in zip(shape, dims):
        if want is None:
            continue
        if isinstance(want, str):
            if want in bound and bound[want] != got:
                raise InputError(f"{name}: expected shape ({_fmt(shape)}), got {tuple(x.shape)}")
            bound[want] = got
        elif want != got:
            raise InputError(f"{name}: expected shape ({_fmt(shape)}), got {tuple(x.shape)}")


def _fmt(shape: Sequence[int | str | None]) -> str:
    return ", ".join("?" if s is None else str(s) for s in shape)


def check_finite(x: torch.Tensor, name: str) -> None:
    """Fail if ``x`` holds NaN or inf, saying how many and where the first one is."""
    bad = ~torch.isfinite(x)
    if bool(bad.any()):
        first = tuple(int(i) for i in torch.nonzero(bad)[0])
        raise InputError(f"{name}: {int(bad.sum())} non-finite values (NaN/inf), first at index {first}")



def check_finite_fast(x: torch.Tensor, name: str) -> None:
    """:func:`check_finite` with numpy's test first for CPU float tensors: a single pass, much faster
    than torch's on a full frame when another thread holds the cores."""
    if x.device.type == "cpu" and x.dtype in (torch.float32, torch.float64) and np.isfinite(x.detach().numpy()).all():
        return
    check_finite(x, name)


def check_image_pair(image_cur: torch.Tensor, image_prev: torch.Tensor) -> None:
    """Fail unless both images are (3, H, W) of the same size and finite (named "image (current)" and
    "image_prev" in the message)."""
    check_shape(image_cur, [3, "H", "W"], "image (current)")
    check_shape(image_prev, [3, "H", "W"], "image_prev")
    check_same_size(image_cur, image_prev, "image (current)", "image_prev")
    check_finite_fast(image_cur, "image (current)")
    check_finite_fast(image_prev, "image_prev")

def check_rotation(R: torch.Tensor, name: str = "R", atol: float = 1e-4) -> None:
    """Fail unless ``R`` (..., 3, 3) is a proper rotation: R^T R = I and det R = +1."""
    check_shape(R, ["*", 3, 3], name)
    check_finite(R, name)
    Rd = R.double()
    eye = torch.eye(3, dtype=Rd.dtype)
    err = (Rd.transpose(-1, -2) @ Rd - eye).abs().amax()
    det = torch.linalg.det(Rd)
    if float(err) > atol or bool(((det - 1).abs() > atol).any()):
        raise InputError(
            f"{name}: not a rotation matrix (max |R^T R - I| = {float(err):.2e}, det = "
            f"{det.flatten()[0].item():.6f}); camera motion must be X_prev = R X_cur + t"
        )


def check_same_size(a: torch.Tensor, b: torch.Tensor, name_a: str, name_b: str) -> None:
    """Fail unless the last two dims (H, W) of ``a`` and ``b`` agree."""
    if tuple(a.shape[-2:]) != tuple(b.shape[-2:]):
        raise InputError(
            f"{name_a} and {name_b} differ in size: {tuple(a.shape[-2:])} vs {tuple(b.shape[-2:])} (H, W)"
        )


def check_number(value: Any, name: str, kind: type = float) -> float | int:
    """``value`` as a ``float`` (or ``int`` with ``kind=int``), or an ``InputError`` naming the option.

    A number, or text that is one (``"1.5"`` from a quoted YAML value), is converted; other text,
    a bool or a list is an error such as ``data.hfov_deg: expected a number, got 'wide'``.
    """
    what = "an integer" if kind is int else "a number"
    if isinstance(value, bool) or not isinstance(value, (int, float, str, np.integer, np.floating)):
        raise InputError(f"{name}: expected {what}, got {value!r}")
    try:
        return kind(value)
    except (TypeError, ValueError):
        # int("2.5") fails as well as int("wide"): both are not an integer.
        raise InputError(f"{name}: expected {what}, got {value!r}") from None


#: ``str(ValueError)`` of Python's number conversions of text (``float("wide")``, ``int("wide")``):
#: the text is the ``repr`` after the colon.
_CONVERSION_ERRORS = ("could not convert string to float: ", "invalid literal for int() with base 10: ")


def numeric_text_error(cfg: Any, error: BaseException) -> InputError | None:
    """The :class:`InputError` naming the option(s) of ``cfg`` behind a failed number conversion.

    An option outside the config groups' schemas (monostixels.config_schema), which refuse text for a
    number as the config is composed, is converted where it is used; text there fails with a bare
    ``ValueError`` that names no option. Given that error, this finds the config leaves holding that
    text and returns ``data.hfov_deg: expected a number, got 'wide'``; None when ``error`` is no such
    conversion error or no option holds the text (then it is not a user's option: a real bug).
    """
    if not isinstance(error, ValueError):
        return None
    msg = str(error)
    prefix = next((p for p in _CONVERSION_ERRORS if msg.startswith(p)), None)
    if prefix is None:
        return None
    text = msg[len(prefix):]
    names = [k for k, v in _leaves(cfg, "") if isinstance(v, str) and repr(v) == text]
    if not names:
        return None
    what = "an integer" if "int()" in prefix else "a number"
    return InputError(f"{', '.join(names)}: expected {what}, got {text}")


def one_line_errors(prog: str) -> Callable[[Callable[[Any], Any]], Callable[[Any], Any]]:
    """Decorate a command's ``main(cfg)`` so that a bad input ends it in one line: ``<prog>: error: <message>``
    on stderr, exit status 1, no traceback (the ``monostixels`` commands and every training script).

    A bad input is an :class:`InputError`, or text given for a number where an option outside the
    config groups' schemas is converted where it is used (:func:`numeric_text_error` names the option).
    Any other exception is a bug and keeps its traceback.
    """
    def wrap(main: Callable[[Any], Any]) -> Callable[[Any], Any]:
        @functools.wraps(main)
        def entry(cfg: Any) -> Any:
            try:
                return main(cfg)
            except ValueError as e:
                error = e if isinstance(e, InputError) else numeric_text_error(cfg, e)
                if error is None:
                    raise
                print(f"{prog}: error: {error}", file=sys.stderr)
                sys.exit(1)
        return entry
    return wrap


def _leaves(node: Any, prefix: str) -> Iterable[tuple[str, Any]]:
    """``(dotted key, value)`` of every leaf of a dict / list / OmegaConf node (interpolations unresolved
    are skipped: they are no user's text)."""
    try:
        from omegaconf import DictConfig, ListConfig, OmegaConf
    except ImportError:  # pragma: no cover - omegaconf ships with the package
        DictConfig = ListConfig = ()  # type: ignore[assignment,misc]
    if isinstance(node, (DictConfig, ListConfig)):
        node = OmegaConf.to_container(node, resolve=False)
    if isinstance(node, dict):
        for k, v in node.items():
            yield from _leaves(v, f"{prefix}.{k}" if prefix else str(k))
    elif isinstance(node, (list, tuple)):
        for i, v in enumerate(node):
            yield from _leaves(v, f"{prefix}[{i}]")
    else:
        yield prefix, node


def config_params(cls: type, cfg: Any, group: str) -> Any:
    """The settings dataclass ``cls`` of the config group ``group`` from its config node.

    A node composed against ``cls`` as its schema (the package config: monostixels.config_schema) is
    converted as it is (``OmegaConf.to_object``: ``cls`` validates the values); any other node, a dict or
    None is first merged onto ``cls``'s schema, which refuses unknown keys and wrong types the way
    Hydra's composition does. Errors are an :class:`InputError` naming ``group.key``.
    """
    from omegaconf import DictConfig, OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    if isinstance(cfg, cls):
        return cfg
    try:
        if not (isinstance(cfg, DictConfig) and isinstance(OmegaConf.get_type(cfg), type)
                and issubclass(OmegaConf.get_type(cfg), cls)):
            if cfg is not None and not hasattr(cfg, "keys"):
                raise InputError(f"{group}: expected a config node of settings, got {type(cfg).__name__}")
            cfg = OmegaConf.merge(OmegaConf.structured(cls), {} if cfg is None else cfg)
        # A key added on the command line (+group.key=...) composes; it is no setting of the schema.
        known = [f.name for f in fields(OmegaConf.get_type(cfg))]
        extra = [str(k) for k in cfg.keys() if k not in known]
        if extra:
            raise InputError(f"{group}.{extra[0]}: unknown setting; known: {', '.join(known)}")
        return OmegaConf.to_object(cfg)
    except OmegaConfBaseException as e:
        raise config_error(e, group) from None


def option_params(schemas: Mapping[str, type], cfg: Any, group: str) -> Any:
    """The settings dataclass of a group whose options differ in their keys (``data``, ``flow``,
    ``semantic``, ``motion``): the schema that ``schemas`` gives the node's ``name``, through
    :func:`config_params`. ``cfg``: a config node, a dict, or already one of the schemas' dataclasses.

    The name, not a composed node's type, picks the schema: a dict or a node without a type (a config
    rebuilt from a plain dict, as ``batch`` hands its clips) reads the same as the composed one.
    """
    if isinstance(cfg, tuple(schemas.values())):
        return cfg
    if cfg is not None and not hasattr(cfg, "keys"):
        raise InputError(f"{group}: expected a config node of settings, got {type(cfg).__name__}")
    name = None if cfg is None else cfg.get("name")
    if name not in schemas:
        raise InputError(f"{group}.name: unknown option {name!r}; choose one of {', '.join(schemas)}")
    return config_params(schemas[name], cfg, group)


def is_unset(cfg: Any, key: str) -> bool:
    """Whether ``cfg`` (a config node or a dict) lacks ``key`` or holds it as null or ``???`` (Hydra's
    mandatory value), before it is read as a dataclass (which refuses ``???`` with a message of its own)."""
    from omegaconf import DictConfig, OmegaConf

    if cfg is None or key not in cfg:
        return True
    if isinstance(cfg, DictConfig):
        return OmegaConf.is_missing(cfg, key) or cfg[key] is None
    return cfg[key] is None or cfg[key] == "???"


def config_error(error: BaseException, group: str = "") -> InputError:
    """One line naming the option for OmegaConf's refusal of a value or key (``error``; ``group``: the
    config group the refused node belongs to, where the error's key is relative to it).

    ``solver.cell_rows: expected an integer, got 'abc'``, ``movers.no_such_key: unknown setting; known: ...``.
    """
    from omegaconf.errors import ConfigKeyError, ValidationError

    key = str(getattr(error, "full_key", "") or getattr(error, "key", "") or "")
    # The key is relative to the refused node's root: the whole config (group in it) or the group's node.
    name = f"{group}.{key}" if group and key and not key.startswith(f"{group}.") else (key or group)
    msg = str(getattr(error, "msg", "") or error).splitlines()[0]
    value = getattr(error, "value", None)
    if isinstance(error, ValidationError):
        m = re.search(r"could not be converted to (\w+)|is not a valid (bool)\b", msg)
        if m:
            kind = m.group(1) or m.group(2)
            what = {"Float": "a number", "Integer": "an integer", "Boolean": "true or false", "bool": "true or false"}.get(kind, kind)
            return InputError(f"{name}: expected {what}, got {value!r}")
        held = getattr(getattr(error, "child_node", None), "_value", lambda: None)()
        if isinstance(held, Enum):  # a Choice field: a name that is none of its members, or no name at all
            return InputError(f"{name}: expected one of {', '.join(type(held).__members__)}, got {_plain(value)!r}")
        if "is not Optional" in msg:
            return InputError(f"{name}: expected a value, got null")
        if "is not a ListConfig, list or tuple" in msg:
            return InputError(f"{name}: expected a list, got {_plain(value)!r}")
        if msg.startswith("Cannot convert") and "to string" in msg:
            return InputError(f"{name}: expected a text, got {_plain(value)!r}")
        return InputError(f"{name}: {msg}")
    if isinstance(error, (ConfigKeyError, AttributeError)) or "not in" in msg:
        known = _known_keys(error)
        return InputError(f"{name}: unknown setting" + (f"; known: {', '.join(known)}" if known else ""))
    return InputError(f"{name}: {msg}")


def _known_keys(error: BaseException) -> list[str]:
    """The keys of the dataclass schema an unknown-key error was raised against (none if not known)."""
    from dataclasses import is_dataclass

    from omegaconf import OmegaConf

    for node in (getattr(error, "child_node", None), getattr(error, "parent_node", None)):
        try:
            t = OmegaConf.get_type(node) if node is not None else None
        except Exception:  # noqa: BLE001 - a node of no known type names no keys
            t = None
        if isinstance(t, type) and is_dataclass(t):
            return [f.name for f in fields(t)]
    t = getattr(error, "object_type", None)
    return [f.name for f in fields(t)] if isinstance(t, type) and is_dataclass(t) else []


def _plain(value: Any) -> Any:
    """An OmegaConf list or dict as the Python one, for a message; any other value as it is."""
    from omegaconf import DictConfig, ListConfig, OmegaConf

    return OmegaConf.to_container(value) if isinstance(value, (DictConfig, ListConfig)) else value
