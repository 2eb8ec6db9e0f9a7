"""Hydra composition of physmend's configuration (compose API, no Hydra app, no chdir).

Configs ship inside the package (``physmend/conf``) when installed and live in ``conf/`` of a
checkout; a user adds a directory of their own (same group layout: ``model/``, ``data/`` …) that is
searched first.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from omegaconf import DictConfig, OmegaConf


class ConfigError(ValueError):
    """A configuration could not be composed; the message names the key or group."""


def _shipped(name: str) -> Path:
    here = Path(__file__).resolve().parent
    for candidate in (here / name, here.parents[1] / name):
        if candidate.is_dir():
            return candidate
    raise ConfigError(f"physmend's {name}/ directory is missing (looked in {here / name} and {here.parents[1] / name})")


def config_dir() -> Path:
    """The shipped Hydra config directory."""
    return _shipped("conf")


def sweeps_dir() -> Path:
    """The shipped directory of named search spaces."""
    return _shipped("sweeps")


def compose(
    overrides: Sequence[str] = (), *, user_config_dir: str | Path | None = None, config_name: str = "config"
) -> DictConfig:
    """Compose ``conf/config.yaml`` with Hydra ``overrides`` (``key=value``, ``group=option``).

    ``user_config_dir`` is an extra config directory searched before the shipped one.
    """
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    extra = list(overrides)
    if user_config_dir is not None:
        user = Path(user_config_dir).expanduser().resolve()
        if not user.is_dir():
            raise ConfigError(f"--config-dir must be an existing directory, but {str(user)!r} is not")
        extra.insert(0, f"hydra.searchpath=[file://{user}]")
    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(version_base="1.3", config_dir=str(config_dir())):
            cfg = hydra_compose(config_name=config_name, overrides=extra)
    except (HydraException, OmegaConfBaseException) as exc:
        raise ConfigError(f"configuration error: {exc}") from exc
    finally:
        GlobalHydra.instance().clear()
    OmegaConf.set_readonly(cfg, False)
    if "hydra" in cfg:
        del cfg["hydra"]
    return cfg


def to_yaml(cfg: DictConfig) -> str:
    return OmegaConf.to_yaml(cfg, resolve=True)
