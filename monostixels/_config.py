"""Composing the package's Hydra config, from the lowest layer so that every module below the pipeline may.

The groups' schemas are registered by the package config itself: ``monostixels.conf`` imports
:mod:`monostixels.config_schema` when Hydra loads it, so nothing here imports the modules the
schemas come from.
"""
from __future__ import annotations

from typing import Sequence

from omegaconf import DictConfig

from monostixels._checks import InputError, config_error

__all__ = ["load_config", "load_group", "composition_error"]


def load_config(overrides: Sequence[str] = ()) -> DictConfig:
    """Compose the package's Hydra config (``conf/config.yaml``) with ``key=value`` overrides.

    For use from Python (notebooks, tests); the ``monostixels`` command does the same through Hydra.
    An unknown key or a value of the wrong type in a group with a schema (monostixels.config_schema) is
    an :class:`InputError` naming the option.
    """
    from contextlib import nullcontext

    from hydra import compose, initialize_config_module
    from hydra.core.global_hydra import GlobalHydra
    from hydra.errors import ConfigCompositionException

    # Under a Hydra app (the command, train/) its search path holds the package config already.
    inside_app = GlobalHydra.instance().is_initialized()
    # Loading the package config (monostixels.conf) registers the groups' schemas.
    with nullcontext() if inside_app else initialize_config_module(config_module="monostixels.conf", version_base="1.3"):
        try:
            return compose(config_name="config", overrides=list(overrides))
        except ConfigCompositionException as e:
            # An unknown key or a wrong type refused by a group's schema: one line naming the option.
            named = composition_error(e)
            if named is None:
                raise
            raise named from None


def load_group(group: str, name: str) -> dict:
    """The packaged option ``<group>=<name>`` as Hydra composes it (its schema's defaults, the YAML's choices and
    overrides), resolved into a plain dict: what a layer below the builder may read of the config.

    Raises:
        InputError: no such option in ``conf/<group>/``.
    """
    from omegaconf import OmegaConf

    try:
        cfg = load_config([f"{group}={name}"])
    except InputError:
        raise
    except Exception as e:  # noqa: BLE001 - Hydra's MissingConfigException and kin: no such option
        raise InputError(f"config {group}={name}: no such option in conf/{group}/ ({str(e).splitlines()[0]})") from None
    return OmegaConf.to_container(cfg[group], resolve=True)  # type: ignore[return-value]


def composition_error(error: BaseException) -> InputError | None:
    """The one-line :class:`InputError` for Hydra's refusal to compose (``error``, a
    ``ConfigCompositionException``) of an unknown key or a value of the wrong type, naming the option;
    None for any other composition error (a missing config file, a bad override's syntax)."""
    from omegaconf.errors import OmegaConfBaseException

    cause = error.__cause__
    if not isinstance(cause, OmegaConfBaseException):
        return None
    return config_error(cause)
