"""Hydra composition of physmend's configuration (compose API, no Hydra app, no chdir).

Configs ship inside the package (``physmend/conf``) when installed and live in ``conf/`` of a
checkout; a user adds a directory of their own (same group layout: ``model/``, ``data/`` …) that is
searched first. The bundled example projects (``examples/<name>/conf``, shipped as
``physmend/examples``) are searched after it, so ``model=<example> data=<example>`` works with no
``--config-dir``.

Project folder
    ``${project:}`` in a ``model`` or ``data`` config stands for the *project folder* of that
    config: the folder above the config directory that holds the file (``my_project/`` for
    ``my_project/conf/model/plant.yaml``). A project can then name its model file and telemetry
    relative to itself (``builder: ${project:}/model.py:build``, ``root: ${project:}/telemetry``)
    and be run from any working directory. It is substituted when the configuration is composed.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from physmend.exceptions import PhysmendError
from physmend.settings import SettingError, shipped_dir


class ConfigError(PhysmendError, ValueError):
    """A configuration could not be composed; the message names the key or group."""


def _shipped(name: str) -> Path:
    try:
        return shipped_dir(name)
    except SettingError as exc:
        raise ConfigError(str(exc)) from None


def config_dir() -> Path:
    """The shipped Hydra config directory."""
    return _shipped("conf")


def sweeps_dir() -> Path:
    """The shipped directory of named search spaces."""
    return _shipped("sweeps")


def example_config_dirs() -> list[Path]:
    """The config directories of the bundled example projects (``examples/*/conf``), sorted."""
    try:
        root = _shipped("examples")
    except ConfigError:
        return []
    return sorted(p for p in root.glob("*/conf") if p.is_dir())


PROJECT = "${project:}"
_PROJECT_GROUPS = ("model", "data")


def _substitute_project(cfg: DictConfig, choices: dict[str, str], search: Sequence[Path]) -> None:
    """Replace ``${project:}`` in the ``model`` and ``data`` groups by their project folders."""
    for group in _PROJECT_GROUPS:
        if group not in cfg or not isinstance(cfg[group], DictConfig):
            continue
        raw = OmegaConf.to_container(cfg[group], resolve=False)
        if PROJECT not in repr(raw):
            continue
        choice = choices.get(group)
        home = next((d for d in search if choice and (d / group / f"{choice}.yaml").is_file()), None)
        if home is None:
            raise ConfigError(
                f"{group} config {choice!r} uses {PROJECT}, which names the folder above the config "
                f"directory holding {group}/{choice}.yaml, but that file is in no config directory "
                f"searched ({', '.join(str(d) for d in search)})"
            )
        folder = str(home.parent)

        def swap(node: Any) -> Any:
            if isinstance(node, str):
                return node.replace(PROJECT, folder)
            if isinstance(node, dict):
                return {k: swap(v) for k, v in node.items()}
            if isinstance(node, list):
                return [swap(v) for v in node]
            return node

        cfg[group] = OmegaConf.create(swap(raw))


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
    search: list[Path] = []
    if user_config_dir is not None:
        user = Path(user_config_dir).expanduser().resolve()
        if not user.is_dir():
            raise ConfigError(f"--config-dir must be an existing directory, but {str(user)!r} is not")
        search.append(user)
    search.extend(d for d in example_config_dirs() if d not in search)
    if search:
        extra.insert(0, "hydra.searchpath=[" + ",".join(f"file://{d}" for d in search) + "]")
    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(version_base="1.3", config_dir=str(config_dir())):
            cfg = hydra_compose(config_name=config_name, overrides=extra, return_hydra_config=True)
    except (HydraException, OmegaConfBaseException) as exc:
        raise ConfigError(_one_line(exc)) from exc
    finally:
        GlobalHydra.instance().clear()
    OmegaConf.set_readonly(cfg, False)
    OmegaConf.set_struct(cfg, False)
    choices = {str(k): str(v) for k, v in OmegaConf.to_container(cfg.hydra.runtime.choices).items()}
    del cfg["hydra"]
    _substitute_project(cfg, choices, [*search, config_dir()])
    from physmend.config_check import check_settings

    try:
        check_settings(cfg)
    except SettingError as exc:
        raise ConfigError(str(exc)) from None
    if "operators" in cfg:
        from physmend.config_check import OperatorError, check_operators

        where = _option_file("operators", choices.get("operators", "default"), [*search, config_dir()])
        try:
            check_operators(OmegaConf.to_container(cfg.operators), where)
        except OperatorError as exc:
            raise ConfigError(str(exc)) from None
    OmegaConf.set_struct(cfg, True)
    return cfg


def _one_line(exc: Exception) -> str:
    """Hydra's composition error as one line: the missing option with the ones there are, or the
    message's own lines joined (its list of search paths left out)."""
    from hydra.errors import MissingConfigException

    if isinstance(exc, MissingConfigException) and exc.missing_cfg_file and exc.options is not None:
        group, _, option = str(exc.missing_cfg_file).rpartition("/")
        if group:
            return (f"configuration error: {group}={option} names no option of config group {group!r}; "
                    f"the options are: {', '.join(sorted(exc.options)) or '(none)'}")
    text = str(exc).split("Config search path:")[0]
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    message = " ".join(lines)
    if len(message) > 400:
        message = message[:397] + "..."
    return f"configuration error: {message}"


def _option_file(group: str, choice: str, dirs: Sequence[Path]) -> str:
    """The file a group's option was composed from (the first of ``dirs`` that has it), for messages."""
    for d in dirs:
        path = Path(d) / group / f"{choice}.yaml"
        if path.is_file():
            return str(path)
    return f"{group}={choice}"


def to_yaml(cfg: DictConfig) -> str:
    return OmegaConf.to_yaml(cfg, resolve=True)
